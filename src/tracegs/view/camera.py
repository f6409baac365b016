"""The browser's camera as a tracegs :class:`~tracegs.data.cameras.Camera`, and back.

viser reports a camera as its pose in the world (``wxyz``: the rotation camera-to-world as a unit
quaternion, ``position``: the centre) with OpenCV axes (x right, y down, z forward), the vertical
field of view ``fov`` (radians) and the canvas aspect ratio (width / height). tracegs cameras are
OpenCV world-to-camera matrices with pinhole intrinsics in pixels, so the axes agree and only the
pose is inverted.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..data.cameras import Camera
from ..physics.so3 import quat_to_rotmat, rotmat_to_quat


def viewmat_from_pose(wxyz, position) -> torch.Tensor:
    """OpenCV world-to-camera [4, 4] of a camera whose camera-to-world rotation is the quaternion
    ``wxyz`` [4] and whose centre is ``position`` [3] (viser's ``client.camera``)."""
    R = quat_to_rotmat(torch.as_tensor(np.asarray(wxyz, dtype=np.float64)))  # columns: camera axes
    p = torch.as_tensor(np.asarray(position, dtype=np.float64))
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = R.T
    viewmat[:3, 3] = -R.T @ p
    return viewmat.to(torch.float32)


def pose_from_viewmat(viewmat: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """(``wxyz`` [4], ``position`` [3]) of an OpenCV world-to-camera [4, 4]: the pose viser places a
    camera frustum or the browser's camera at."""
    R, t = viewmat[:3, :3].double().cpu(), viewmat[:3, 3].double().cpu()
    return rotmat_to_quat(R.T).numpy(), (-R.T @ t).numpy()


def camera_from_view(wxyz, position, fov_y: float, aspect: float, width: int) -> Camera:
    """The pinhole camera ``width`` pixels wide (the height from ``aspect`` = width / height) with the
    vertical field of view ``fov_y`` (radians), square pixels and the principal point at the centre,
    at the pose (``wxyz``, ``position``)."""
    height = max(1, round(width / aspect))
    f = 0.5 * height / math.tan(0.5 * fov_y)
    K = torch.tensor([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float32)
    return Camera(viewmat_from_pose(wxyz, position), K, width, height)


def vertical_fov(camera: Camera) -> float:
    """Vertical field of view (radians) of ``camera``."""
    return 2.0 * math.atan(0.5 * camera.height / float(camera.K[1, 1]))
