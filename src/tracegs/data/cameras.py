"""Pinhole cameras in the convention every backend of ``tracegs.render.rasterize`` takes.

World-to-camera matrices use OpenCV axes (x right, y down, z forward); intrinsics are in pixels and
the centre of pixel (row i, col j) is at (j + 0.5, i + 0.5). Blender/NeRF files store camera-to-world
in OpenGL axes (x right, y up, z backward); :func:`opengl_c2w_to_viewmat` converts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch


@dataclass
class Camera:
    """One calibrated view: extrinsics, intrinsics and image size."""

    viewmat: torch.Tensor  # [4, 4] world-to-camera, OpenCV axes
    K: torch.Tensor  # [3, 3] intrinsics in pixels
    width: int
    height: int

    @property
    def center(self) -> torch.Tensor:
        """Camera centre in world coordinates, [3]."""
        R, t = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ t

    def to(self, device: torch.device | str) -> Camera:
        return Camera(self.viewmat.to(device), self.K.to(device), self.width, self.height)

    def scaled(self, factor: float) -> Camera:
        """The same camera for an image resized by ``factor`` (e.g. 0.5 for half resolution)."""
        K = self.K.clone()
        K[:2] *= factor
        return Camera(self.viewmat, K, round(self.width * factor), round(self.height * factor))


def focus_point(viewmats: torch.Tensor, min_spread: float = 0.02) -> torch.Tensor | None:
    """The point [3] closest, in least squares, to the optical axes of cameras ``viewmats`` [C, 4, 4]
    (OpenCV world-to-camera): where an inward-facing capture looks.

    None when the axes are too close to parallel to meet (the smallest eigenvalue of the mean
    projector onto the axes' normal planes below ``min_spread``: a forward-facing capture) or when the
    point lies behind most of the cameras.
    """
    R, t = viewmats[:, :3, :3].double(), viewmats[:, :3, 3].double()
    centers = -(R.transpose(1, 2) @ t[..., None])[..., 0]
    forward = R[:, 2]  # the camera's +z axis in world coordinates
    normal = torch.eye(3, dtype=torch.float64) - forward[:, :, None] * forward[:, None, :]
    A, b = normal.mean(0), (normal @ centers[..., None]).mean(0)[:, 0]
    if float(torch.linalg.eigvalsh(A)[0]) < min_spread:
        return None
    point = torch.linalg.solve(A, b)
    in_front = ((point - centers) * forward).sum(-1) > 0
    return point if in_front.double().mean() > 0.5 else None


def opengl_c2w_to_viewmat(c2w: torch.Tensor) -> torch.Tensor:
    """Blender/OpenGL camera-to-world [4, 4] -> OpenCV world-to-camera [4, 4]."""
    c2w = c2w.clone().to(torch.float64)
    c2w[:3, 1:3] *= -1  # flip camera y (up -> down) and z (backward -> forward)
    return torch.linalg.inv(c2w).to(torch.float32)


def intrinsics_from_fov(fov_x: float, width: int, height: int, fov_y: float | None = None) -> torch.Tensor:
    """Intrinsics [3, 3] of a centred pinhole with horizontal field of view ``fov_x`` (radians)."""
    fx = 0.5 * width / math.tan(0.5 * fov_x)
    fy = fx if fov_y is None else 0.5 * height / math.tan(0.5 * fov_y)
    return torch.tensor([[fx, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float32)


def look_at_viewmat(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> torch.Tensor:
    """OpenCV world-to-camera [4, 4] for a camera at ``eye`` looking at ``target``, ``up`` roughly up."""
    eye, target, up = (torch.as_tensor(v, dtype=torch.float32) for v in (eye, target, up))
    forward = torch.nn.functional.normalize(target - eye, dim=0)
    right = torch.nn.functional.normalize(torch.linalg.cross(forward, up), dim=0)
    down = torch.linalg.cross(forward, right)
    R = torch.stack([right, down, forward])  # rows: camera axes in world coordinates
    viewmat = torch.eye(4)
    viewmat[:3, :3] = R
    viewmat[:3, 3] = -R @ eye
    return viewmat


def scene_extent_from_cameras(centers: torch.Tensor) -> float:
    """3DGS's ``spatial_lr_scale``: 1.1 x the radius of the camera centres around their mean."""
    return 1.1 * float((centers - centers.mean(0)).norm(dim=-1).max().clamp_min(1e-6))
