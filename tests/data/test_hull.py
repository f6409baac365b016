"""The visual hull of a generated capture: carved from its foreground masks, it holds the object and
little else."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tracegs.data.cameras import Camera, intrinsics_from_fov, look_at_viewmat
from tracegs.data.hull import hull_colours, project, visual_hull

CENTRE, RADIUS = torch.tensor([0.1, -0.2, 0.05]), 0.3


def _cameras(n: int = 10, size: int = 48) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        eye = (2.0 * math.cos(a), 2.0 * math.sin(a), 0.6 * (-1) ** i)
        cams.append(
            Camera(look_at_viewmat(eye, CENTRE.tolist()), intrinsics_from_fov(0.7, size, size), size, size)
        )
    return cams


def _sphere_mask(camera: Camera) -> np.ndarray:
    """[H, W] the pixels whose centre ray meets the sphere."""
    j, i = torch.meshgrid(torch.arange(camera.width) + 0.5, torch.arange(camera.height) + 0.5, indexing="xy")
    pix = torch.stack([j, i, torch.ones_like(j)], -1).reshape(-1, 3)
    R = camera.viewmat[:3, :3]
    rays = (pix @ torch.linalg.inv(camera.K).T) @ R  # world directions (R^T d)
    rays = rays / rays.norm(dim=-1, keepdim=True)
    to_centre = CENTRE - camera.center
    along = rays @ to_centre
    miss = (to_centre.norm() ** 2 - along**2).sqrt()
    return (miss < RADIUS).reshape(camera.height, camera.width).numpy()


def test_the_hull_of_a_sphere_holds_the_sphere_and_little_else():
    cams = _cameras()
    masks = [_sphere_mask(c) for c in cams]
    assert all(0.05 < m.mean() < 0.6 for m in masks)
    box = torch.stack([CENTRE - 1.0, CENTRE + 1.0])
    points = visual_hull(cams, masks, box, resolution=48)
    step = 2.0 / 48
    distance = (points - CENTRE).norm(dim=-1)
    assert len(points) > 100
    assert float(distance.max()) < 1.25 * RADIUS + step  # nothing far from the object
    # every voxel well inside the sphere is kept
    axes = [CENTRE[i] - 1.0 + step * (torch.arange(48) + 0.5) for i in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    core = grid[(grid - CENTRE).norm(dim=-1) < RADIUS - 2 * step]
    kept = {tuple(p) for p in torch.round(points / step).long().tolist()}
    assert all(tuple(p) in kept for p in torch.round(core / step).long().tolist())


def test_one_camera_missing_the_object_does_not_cut_it_away():
    cams = _cameras()
    masks = [_sphere_mask(c) for c in cams]
    masks[3] = np.zeros_like(masks[3])  # a segmenter that missed it in one view
    box = torch.stack([CENTRE - 1.0, CENTRE + 1.0])
    assert len(visual_hull(cams, masks, box, resolution=32, tolerance=0.15)) > 50
    assert len(visual_hull(cams, masks, box, resolution=32, tolerance=0.0)) == 0


def test_hull_colours_and_bad_masks():
    cams = _cameras(4)
    points = CENTRE[None] + 0.05 * torch.randn(20, 3)
    images = [torch.full((c.height, c.width, 3), 0.25) for c in cams]
    assert torch.allclose(hull_colours(points, cams, images), torch.full((20, 3), 0.25))
    uv, z = project(CENTRE[None], cams[0])
    assert (z > 0).all() and torch.allclose(uv, torch.tensor([[24.0, 24.0]]), atol=1e-3)
    with pytest.raises(ValueError, match="mask of"):
        visual_hull(cams, [np.zeros((5, 5), bool)] * 4, torch.stack([CENTRE - 1, CENTRE + 1]))
