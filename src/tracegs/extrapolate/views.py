"""The training images the calibration scores candidate futures on (never the evaluation splits)."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import torch

from ..data.scene import load_image, load_scene
from ..physics.so3 import quat_normalize


def training_frames_by_time(data: Path, downscale: int, t_max: float):
    """The training scene and its frames with time <= ``t_max`` grouped by time: ``(scene, {t: frames})``
    with the times in increasing order."""
    scene = load_scene(Path(data), "train", downscale)
    by_time: dict[float, list] = defaultdict(list)
    for f in scene.frames:
        if f.time <= t_max + 1e-9:
            by_time[f.time].append(f)
    return scene, dict(sorted(by_time.items()))


class TrainingViews:
    """The training images at the times in (``t_from``, ``t_to``] up to ``t_max`` and f_defo's state at each:
    ``views`` {t: [(camera, image)]}, ``deformed`` {t: state}."""

    def __init__(self, model, data: Path, downscale: int, t_from: float, t_to: float, t_max: float):
        scene, by_time = training_frames_by_time(data, downscale, t_max)
        dev = model.aabb.device
        self.model = model
        self.background = torch.tensor(scene.background, device=dev)
        self.views = {
            t: [(f.camera.to(dev), load_image(f, scene.background).to(dev)) for f in frames]
            for t, frames in by_time.items()
            if t_from + 1e-9 < t <= t_to + 1e-9
        }
        self.deformed = {}
        for t in self.views:
            state = model.deform(t)
            self.deformed[t] = {**state, "quats": quat_normalize(state["quats"])}

    def with_part(self, t: float, rows: torch.Tensor, means: torch.Tensor, quats: torch.Tensor) -> dict:
        """f_defo's state at ``t`` with the Gaussians ``rows`` at ``means``, ``quats``."""
        state = self.deformed[t]
        all_means, all_quats = state["means"].clone(), state["quats"].clone()
        all_means[rows], all_quats[rows] = means, quats
        return {**state, "means": all_means, "quats": all_quats}

    def render(self, state: dict, camera) -> torch.Tensor:
        return self.model.render(state, camera, self.model.sh_degree, self.background).image
