"""Initial points from foreground masks: the visual hull of a set of calibrated views.

A capture without a point cloud (no SfM, no depth) still says where its moving objects are: each
camera's foreground mask is a cone of rays, and the object lies in the intersection of the cones
(the visual hull). ``visual_hull`` carves a voxel grid over a box: a voxel is kept when enough
cameras see it and (nearly) all of those see it inside their mask. Its points seed the Gaussians of
the foreground, where a random box would spend most of them on empty space.

Written here rather than taken from a library: the carving is twenty lines of projection on our own
cameras, and the libraries that carve (Open3D, kaolin) bring a large dependency for it.

M: kept voxels, C: cameras.
"""

from __future__ import annotations

import numpy as np
import torch

from .cameras import Camera


def project(points: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor]:
    """(pixel coordinates [N, 2] (x right, y down; pixel centres at +0.5), depth [N]) of world
    ``points`` [N, 3] seen by ``camera``."""
    R, t = camera.viewmat[:3, :3].to(points), camera.viewmat[:3, 3].to(points)
    cam = points @ R.T + t
    z = cam[:, 2]
    uv = cam @ camera.K.to(points).T
    return uv[:, :2] / z.clamp_min(1e-9)[:, None], z


def pixels(points: torch.Tensor, camera: Camera) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(row [N], column [N], visible [N] bool) of the pixel each of ``points`` [N, 3] falls in, seen by
    ``camera``; visible: in front of it and inside its image."""
    uv, z = project(points, camera)
    col, row = uv[:, 0].floor().long(), uv[:, 1].floor().long()
    visible = (z > 0) & (col >= 0) & (col < camera.width) & (row >= 0) & (row < camera.height)
    return row, col, visible


def visual_hull(
    cameras: list[Camera],
    masks: list[np.ndarray],
    box: torch.Tensor,
    resolution: int = 64,
    min_views: int = 3,
    tolerance: float = 0.1,
) -> torch.Tensor:
    """[M, 3] centres of the voxels of ``box`` [2, 3] (min, max corners; ``resolution`` voxels along
    its longest side) that at least ``min_views`` of ``cameras`` see in front of them and inside their
    image, and that all but ``tolerance`` of those see inside their foreground mask (``masks``: one
    [H, W] bool per camera, at the camera's size): masks from a segmenter miss a few pixels, and one
    camera's miss must not cut a hole through the object."""
    box = torch.as_tensor(box, dtype=torch.float32)
    size = box[1] - box[0]
    step = float(size.max()) / resolution
    axes = [
        box[0, i] + step * (torch.arange(max(int(round(float(size[i]) / step)), 1)) + 0.5) for i in range(3)
    ]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    return grid[in_hull(grid, cameras, masks, min_views, tolerance)]


def in_hull(
    points: torch.Tensor,
    cameras: list[Camera],
    masks: list[np.ndarray],
    min_views: int = 3,
    tolerance: float = 0.1,
) -> torch.Tensor:
    """[N] bool: which of ``points`` [N, 3] lie in the visual hull of ``masks`` seen by ``cameras``
    (the rule of ``visual_hull``)."""
    if len(cameras) != len(masks):
        raise ValueError(f"{len(cameras)} cameras and {len(masks)} masks")
    seen = torch.zeros(len(points), dtype=torch.int32)
    inside = torch.zeros(len(points), dtype=torch.int32)
    for camera, mask in zip(cameras, masks, strict=True):
        mask = torch.as_tensor(np.asarray(mask, dtype=bool))
        if mask.shape != (camera.height, camera.width):
            raise ValueError(f"a mask of {tuple(mask.shape)} for a camera of {camera.height}x{camera.width}")
        row, col, visible = pixels(points, camera)
        seen += visible.int()
        hit = torch.zeros_like(visible)
        hit[visible] = mask[row[visible], col[visible]]
        inside += hit.int()
    return (seen >= min_views) & (inside >= torch.ceil((1.0 - tolerance) * seen).int())


def in_any_hull(root, frames: list, points: torch.Tensor, every: int = 4, **rule) -> torch.Tensor | None:
    """[N] bool: which of ``points`` [N, 3] lie in the visual hull of the foreground masks at one or
    more of every ``every``-th time of ``frames`` (the space the subject sweeps over them: what lies
    outside stands still); None when no time has masks from 3 cameras. ``rule``: of ``in_hull``."""
    times = sorted({f.time for f in frames})[::every]
    inside, any_time = torch.zeros(len(points), dtype=torch.bool), False
    for t in times:
        have = [(f.camera.to("cpu"), m) for f, m in views_at(root, frames, t) if m is not None]
        if len(have) >= rule.get("min_views", 3):
            inside |= in_hull(points.cpu(), [c for c, _ in have], [m for _, m in have], **rule)
            any_time = True
    return inside.to(points.device) if any_time else None


def hull_colours(points: torch.Tensor, cameras: list[Camera], images: list[torch.Tensor]) -> torch.Tensor:
    """[M, 3] the mean colour of ``points`` [M, 3] over the ``images`` ([H, W, 3] in [0, 1]) of the
    ``cameras`` that see them (0.5 where none does)."""
    total = torch.zeros(len(points), 3)
    count = torch.zeros(len(points), 1)
    for camera, image in zip(cameras, images, strict=True):
        row, col, visible = pixels(points, camera)
        total[visible] += image[row[visible], col[visible]].float()
        count[visible] += 1
    return torch.where(count > 0, total / count.clamp_min(1), torch.full_like(total, 0.5))


def hull_points(
    root, frames: list, box: torch.Tensor, resolution: int = 64, min_views: int = 3, tolerance: float = 0.1
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(points [M, 3], colours [M, 3]) of the visual hull of the earliest time of ``frames`` (a split's
    ``Frame`` list) from their foreground masks (``data.masks``), coloured from their images; None when
    fewer than ``min_views`` of those frames have a mask or nothing is kept."""
    from .frames import load_image

    have = [(f, m) for f, m in views_at(root, frames, min(f.time for f in frames)) if m is not None]
    if len(have) < min_views:
        return None
    cameras = [f.camera.to("cpu") for f, _ in have]
    points = visual_hull(cameras, [m for _, m in have], box.cpu(), resolution, min_views, tolerance)
    if len(points) == 0:
        return None
    images = [load_image(f).cpu() for f, _ in have]
    return points, hull_colours(points, cameras, images)


def views_at(root, frames: list, t: float) -> list[tuple]:
    """(frame, foreground mask [H, W] bool or None) of each of ``frames`` taken at time ``t``."""
    from .masks import read_foreground

    return [(f, read_foreground(root, f)) for f in frames if f.time == t]
