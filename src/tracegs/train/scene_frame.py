"""Where a capture lies, for the parts of training sized for the Blender layout: the cube of the random
initial Gaussians (``default_aabb``) and the frame the fields see positions in (``field_frame``), both
read off the cameras (``camera_frame``: the point they look at and their distance from it)."""

from __future__ import annotations

import torch

from ..config import TrainConfig
from ..data.cameras import focus_point
from ..data.dataset import ViewDataset

# Distance from the Blender / D-NeRF synthetic cameras to the point they look at (the origin), for
# which ``init_extent`` (1.3, the random-init cube of 3DGS and Deformable 3DGS) is made.
BLENDER_CAMERA_DISTANCE = 4.031


def default_aabb(cfg: TrainConfig, data: ViewDataset) -> torch.Tensor:
    """The box of the random initial Gaussians (and of TRACE_4dgs's HexPlane): the dataset's ``aabb``
    if it gives one, else (``init_box = "cameras"``) a cube around the point the cameras look at,
    sized to their distance from it, else the cube of half-size ``init_extent`` around the origin.

    The camera-based cube is rounded (centre to 0.1% of the camera distance, half-size to three
    significant digits), so the Blender layout gives exactly the origin's +/- 1.3 cube.
    """
    if data.scene.aabb is not None:
        return data.scene.aabb.float()
    center, half = torch.zeros(3, dtype=torch.float64), cfg.init_extent
    frame = camera_frame(data) if cfg.init_box == "cameras" else None
    if frame is not None:
        center, half = frame[0], float(f"{cfg.init_extent * frame[1]:.3g}")
    return torch.stack([center - half, center + half]).float()


def camera_frame(data: ViewDataset) -> tuple[torch.Tensor, float] | None:
    """Where an inward-facing capture looks and its size against the Blender layout: the point
    [3] (float64) the cameras look at, rounded to 0.1% of their median distance from it, and that
    distance / 4.031. The Blender and D-NeRF scenes give the origin and 1 (up to rounding). None for
    a forward-facing capture, whose optical axes do not meet."""
    viewmats = torch.stack([v.camera.viewmat.cpu() for v in data.views])
    point = focus_point(viewmats)
    if point is None:
        return None
    distance = float((data.camera_centers().double() - point).norm(dim=-1).median())
    step = 1e-3 * distance
    return torch.round(point / step) * step + 0.0, distance / BLENDER_CAMERA_DISTANCE  # + 0.0: no -0.0


def capture_scale(data: ViewDataset) -> float:
    """The size of a capture against the Blender layout (``camera_frame``), to three digits; 1 for a
    forward-facing one."""
    frame = camera_frame(data)
    return 1.0 if frame is None else float(f"{frame[1]:.3g}")


def field_frame(cfg: TrainConfig, data: ViewDataset) -> tuple[torch.Tensor, float]:
    """Centre [3] and scale of the frame the fields see positions in (``TraceModel.set_field_frame``).

    ``world``: the world's coordinates, as the paper and Deformable 3DGS use them (made for the
    Blender layout). ``cameras``: the camera frame of ``camera_frame`` (the point the cameras look at,
    their distance / 4.031, to three digits), so a capture at any scale and place looks to the fields
    like a Blender scene. ``auto``: the world's when the camera-based cube of the random
    initialisation (half-size 1.3 x the scale) already lies within +/- 2 units of the origin and is
    at least 0.4 units across (the Blender and D-NeRF scenes, our synthetic ones), else ``cameras``.
    A forward-facing capture keeps the world's frame.
    """
    world = (torch.zeros(3), 1.0)
    frame = camera_frame(data) if cfg.field_frame != "world" else None
    if frame is None:
        return world
    center, scale = frame[0].float(), float(f"{frame[1]:.3g}")
    half = cfg.init_extent * scale
    if cfg.field_frame == "auto" and float(center.abs().max()) + half <= 2.0 and half >= 0.4:
        return world
    return center, scale
