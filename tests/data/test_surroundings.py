"""The surroundings' initial points lie on the walls the cameras see, not in front of any camera."""

from __future__ import annotations

import math

import numpy as np
import torch

from tracegs.data.cameras import Camera, intrinsics_from_fov, look_at_viewmat
from tracegs.data.surroundings import sphere_directions, surroundings

WALL = 2.0  # radius of the room, a textured sphere round the origin


def wall_colour(points: torch.Tensor) -> torch.Tensor:
    """A texture on the sphere that differs from one place to the next (a wrong depth disagrees)."""
    d = torch.nn.functional.normalize(points, dim=-1)
    theta, phi = torch.acos(d[:, 2].clamp(-1, 1)), torch.atan2(d[:, 1], d[:, 0])
    return torch.stack(
        [0.5 + 0.5 * torch.sin(9 * theta), 0.5 + 0.5 * torch.cos(7 * phi), 0.5 + 0.4 * d[:, 2]], -1
    )


def render_room(camera: Camera) -> torch.Tensor:
    """[H, W, 3] the room seen by ``camera`` (a ray-sphere intersection per pixel)."""
    H, W = camera.height, camera.width
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys, torch.ones_like(xs)], -1).reshape(-1, 3)
    dirs = pix @ torch.linalg.inv(camera.K).T @ camera.viewmat[:3, :3]  # camera rays in the world
    dirs = torch.nn.functional.normalize(dirs, dim=-1)
    o = camera.center
    b = dirs @ o
    s = -b + torch.sqrt(b * b - (o @ o - WALL**2))  # the far root: the camera is inside the room
    return wall_colour(o + s[:, None] * dirs).reshape(H, W, 3)


def ring_of_cameras(count: int = 8, radius: float = 1.6) -> list[Camera]:
    cams = []
    for i in range(count):
        a = 2 * math.pi * i / count
        eye = (radius * math.cos(a), radius * math.sin(a), 0.3 * (-1) ** i)
        cams.append(Camera(look_at_viewmat(eye), intrinsics_from_fov(1.4, 48, 40), 48, 40))
    return cams


def test_sphere_directions_are_unit_and_spread():
    d = sphere_directions(500)
    assert torch.allclose(d.norm(dim=-1), torch.ones(500), atol=1e-5)
    assert float(d.mean(0).norm()) < 0.01


def test_surroundings_lie_on_the_wall_the_cameras_see():
    cams = ring_of_cameras()
    images = [render_room(c) for c in cams]
    points, colours = surroundings(cams, images, [None] * len(cams), torch.zeros(3), count=3000)
    assert len(points) > 1000
    radius = points.norm(dim=-1)
    # candidates are 0.1 x the cameras' distance (1.6) apart: the wall's 1.25 lies between two
    assert float((radius - WALL).abs().median()) < 0.1
    assert float((colours - wall_colour(points)).abs().mean()) < 0.08
    centres = torch.stack([c.center for c in cams])
    assert float(torch.cdist(points, centres).min()) > 0.15 * 1.6


def test_the_foreground_masks_keep_the_subject_out():
    cams = ring_of_cameras()
    images = [render_room(c) for c in cams]
    masks = [np.zeros((c.height, c.width), dtype=bool) for c in cams]
    for mask in masks:  # a subject fills the middle of every view: painted black, masked out
        mask[10:30, 14:34] = True
    for image, mask in zip(images, masks, strict=True):
        image[torch.as_tensor(mask)] = 0.0
    masked = surroundings(cams, images, masks, torch.zeros(3), count=3000)
    unmasked = surroundings(cams, images, [None] * len(cams), torch.zeros(3), count=3000)
    error = [float((c - wall_colour(p)).abs().mean()) for p, c in (masked, unmasked)]
    assert error[0] < 0.08 and error[1] > error[0] + 0.02  # the subject's black is not the wall's
