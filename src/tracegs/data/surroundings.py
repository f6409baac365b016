"""Initial points for the static surroundings of an inward-facing capture (a dome, a room).

A rig of cameras round a subject sees, behind it, the walls and floor the cameras stand on or near.
Random Gaussians in a box about the subject never reach them, and random Gaussians in a larger box
put blobs right in front of some camera, which that camera alone then fits (a floater its
neighbours never agree with). Here every direction from the point the cameras look at gets one
point, at the distance along it where the cameras agree best on its colour: candidate distances are
fractions of the cameras' median distance from that point (the walls they stand at lie near 1; a
floor below them nearer), each scored by the variance of the colours the cameras that see it show
there, outside their foreground masks when there are masks (the subject is not the surroundings).
The photo-consistency of voxel colouring, along rays from the centre only: one depth per direction.

Written here: the sweep is projection on our own cameras (``hull.pixels``); a multi-view stereo
library would bring a large dependency for a start that the optimisation refines anyway.

P: directions (points), C: cameras, R: candidate distances.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .cameras import Camera
from .hull import pixels


def sphere_directions(count: int) -> torch.Tensor:
    """[count, 3] unit vectors spread evenly over the sphere (a Fibonacci lattice)."""
    i = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / count
    phi = math.pi * (3.0 - math.sqrt(5.0)) * i
    r = (1.0 - z * z).clamp_min(0).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], -1).float()


def surroundings(
    cameras: list[Camera],
    images: list[torch.Tensor],
    masks: list[np.ndarray | None],
    centre: torch.Tensor,
    count: int = 20_000,
    fractions: tuple[float, ...] = tuple(np.round(np.linspace(0.3, 1.6, 14), 3)),
    min_views: int = 2,
    camera_clearance: float = 0.15,
    far_preference: float = 1e-3,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(points [M, 3], colours [M, 3]) of the surroundings seen by ``cameras`` (images [H, W, 3] in
    [0, 1], foreground ``masks`` [H, W] bool or None) about ``centre`` [3] (module docstring): up to
    ``count`` directions, each kept at the candidate distance (``fractions`` of the cameras' median
    distance from ``centre``) whose colour varies least over the cameras that see it there, among
    those that ``min_views`` cameras see; points nearer a camera than ``camera_clearance`` times that
    distance are left out (they would fill that camera's view)."""
    centre = torch.as_tensor(centre, dtype=torch.float32)
    centres = torch.stack([c.center for c in cameras]).float()
    distance = float((centres - centre).norm(dim=-1).median())
    dirs = sphere_directions(count)
    costs, means = [], []
    for fraction in fractions:
        points = centre + fraction * distance * dirs
        total, squares = torch.zeros(count, 3), torch.zeros(count, 3)
        seen = torch.zeros(count)
        for camera, image, mask in zip(cameras, images, masks, strict=True):
            row, col, visible = pixels(points, camera)
            if mask is not None:
                visible[visible.clone()] &= ~torch.as_tensor(mask)[row[visible], col[visible]]
            colour = image[row[visible], col[visible]].float()
            total[visible] += colour
            squares[visible] += colour * colour
            seen[visible] += 1
        mean = total / seen.clamp_min(1)[:, None]
        variance = (squares / seen.clamp_min(1)[:, None] - mean * mean).clamp_min(0).sum(-1)
        # where colours agree at several distances (a uniform wall), the farthest: behind the cameras
        # a point draws the wall as well for those across the rig and never fills one camera's view
        cost = variance + far_preference * (max(fractions) - fraction)
        costs.append(torch.where(seen >= min_views, cost, torch.full_like(cost, math.inf)))
        means.append(mean)
    costs = torch.stack(costs)  # [R, P]
    best = costs.argmin(0)
    keep = torch.isfinite(costs.min(0).values)
    fraction = torch.tensor(fractions, dtype=torch.float32)[best]
    points = centre + (fraction * distance)[:, None] * dirs
    colours = torch.stack(means)[best, torch.arange(count)]
    clearance = torch.cdist(points, centres).min(-1).values > camera_clearance * distance
    keep &= clearance
    return points[keep], colours[keep]
