"""The Gaussians a training starts from: the scene's points (``points3d.ply``, e.g. SfM), else random
Gaussians in the box (3DGS's random init), to which a capture with foreground masks may add the visual
hull of its subject (``init_hull``, ``data/hull.py``) and any inward-facing capture its surroundings
(``init_surroundings``, ``data/surroundings.py``), both from the first time's training images."""

from __future__ import annotations

from pathlib import Path

import torch

from ..config import TrainConfig
from ..data.scene import load_scene
from ..models.gaussians import create_gaussians, random_gaussians


def initial_gaussians(
    cfg: TrainConfig, aabb: torch.Tensor, device, log=print, frames: list | None = None
) -> torch.nn.ParameterDict:
    """The initial Gaussians of a run (module docstring); ``log`` says what the hull and the
    surroundings gave; ``frames``: the training split's frames when they are already loaded."""
    ply = Path(cfg.data) / "points3d.ply"
    if ply.is_file():
        from ..data.points import read_points

        points, colors = read_points(ply)
        return create_gaussians(points.to(device), colors.to(device), cfg.sh_degree)
    background = random_gaussians(cfg.init_points, aabb, cfg.sh_degree)
    if not (cfg.init_hull or cfg.init_surroundings):
        return background
    frames = frames if frames is not None else load_scene(cfg.data, "train", cfg.downscale).frames
    parts = []
    if cfg.init_hull:
        parts.append(_hull(cfg, frames, aabb, log))
    if cfg.init_surroundings:
        parts.append(_surroundings(cfg, frames, log))
    added = [create_gaussians(p.to(device), c.to(device), cfg.sh_degree) for p, c in filter(None, parts)]
    if not added:
        return background
    log(f"{cfg.init_points} random initial Gaussians in the box")
    bg = background.to(device)
    return torch.nn.ParameterDict(
        {
            name: torch.nn.Parameter(torch.cat([*(a[name].detach() for a in added), bg[name].detach()]))
            for name in bg
        }
    )


def _hull(cfg: TrainConfig, frames: list, aabb: torch.Tensor, log):
    from ..data.hull import hull_points

    hull = hull_points(cfg.data, frames, aabb.cpu(), cfg.hull_resolution)
    if hull is None:
        log(
            f"{cfg.data}: no foreground masks at the first time (seg/ or masks/): no visual hull, random initial Gaussians"
        )
    else:
        log(f"visual hull of the foreground masks: {len(hull[0])} initial Gaussians")
    return hull


def _surroundings(cfg: TrainConfig, frames: list, log):
    from ..data.cameras import focus_point
    from ..data.frames import load_image
    from ..data.hull import views_at
    from ..data.surroundings import surroundings

    first = views_at(cfg.data, frames, min(f.time for f in frames))
    cameras = [f.camera.to("cpu") for f, _ in first]
    centre = focus_point(torch.stack([c.viewmat for c in cameras]))
    if centre is None or len(first) < 2:
        log(f"{cfg.data}: the cameras do not look at one point: no surroundings")
        return None
    images = [load_image(f).cpu() for f, _ in first]
    masks = [m for _, m in first]
    points, colours = surroundings(cameras, images, masks, centre.float(), cfg.init_surroundings)
    log(f"surroundings seen by the first time's cameras: {len(points)} initial Gaussians")
    return points, colours
