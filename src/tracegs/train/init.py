"""The Gaussians a training starts from: the scene's points (``points3d.ply``, e.g. SfM), or with
``init_hull`` the visual hull of its foreground masks (``data/hull.py``) plus random Gaussians in the
box for the surroundings, else random Gaussians in the box (3DGS's random init)."""

from __future__ import annotations

from pathlib import Path

import torch

from ..config import TrainConfig
from ..data.scene import load_scene
from ..models.gaussians import create_gaussians, random_gaussians


def initial_gaussians(
    cfg: TrainConfig, aabb: torch.Tensor, device, log=print, frames: list | None = None
) -> torch.nn.ParameterDict:
    """The initial Gaussians of a run (module docstring); ``log`` says what the hull gave; ``frames``:
    the training split's frames when they are already loaded."""
    ply = Path(cfg.data) / "points3d.ply"
    if ply.is_file():
        from ..data.points import read_points

        points, colors = read_points(ply)
        return create_gaussians(points.to(device), colors.to(device), cfg.sh_degree)
    background = random_gaussians(cfg.init_points, aabb, cfg.sh_degree)
    if not cfg.init_hull:
        return background
    from ..data.hull import hull_points

    frames = frames if frames is not None else load_scene(cfg.data, "train", cfg.downscale).frames
    hull = hull_points(cfg.data, frames, aabb.cpu(), cfg.hull_resolution)
    if hull is None:
        log(f"{cfg.data}: no foreground masks at the first time (seg/ or masks/): random initial Gaussians")
        return background
    points, colors = hull
    log(f"visual hull of the foreground masks: {len(points)} initial Gaussians, {cfg.init_points} random")
    fg = create_gaussians(points.to(device), colors.to(device), cfg.sh_degree)
    bg = background.to(device)
    return torch.nn.ParameterDict(
        {name: torch.nn.Parameter(torch.cat([fg[name].detach(), bg[name].detach()])) for name in fg}
    )
