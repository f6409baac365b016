"""Post-training choices made on the training images only (never on the evaluation splits).

``choose_freeze_threshold``: METHOD.md allows Gaussians that never move during training to be frozen
at their state when extrapolating. Without it, f_trd's smoothness across an object's boundary lets a
static part creep along with its moving neighbour (measured on ``fan``: the static base drifted as
far as the blades' own trajectory error). Below which displacement a Gaussian counts as static depends
on the scene's scale and on how noisy f_defo is, so the threshold is chosen per run by a
pseudo-extrapolation on the training data: start the physics ``horizon`` frames before the last
training time, integrate to the last few training times, and score the training cameras there.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import torch

from ..data.blender import load_image, load_scene
from ..eval.metrics import mae_psnr, mse

# Candidate thresholds as fractions of the scene extent (3DGS's camera radius); 0 = freeze nothing.
FREEZE_FRACTIONS = (0.0, 0.001, 0.002, 0.005, 0.01, 0.02)


@torch.no_grad()
def choose_freeze_threshold(
    model,
    data: Path,
    downscale: int,
    t_max: float,
    extent: float,
    horizon_frames: int = 16,
    target_times: int = 3,
) -> tuple[float, dict[float, float]]:
    """The threshold (scene units) with the best PSNR of the training cameras at the last
    ``target_times`` training times, extrapolated from ``horizon_frames`` frames before t_max.

    Returns ``(threshold, {threshold: psnr})``; ties go to the smaller threshold. Models without both
    fields (DefGS, static, "no f_defo") return 0.
    """
    if model.dynamics is None or model.deformation is None:
        return 0.0, {}
    scene = load_scene(Path(data), "train", downscale)
    by_time: dict[float, list] = defaultdict(list)
    for f in scene.frames:
        if f.time <= t_max + 1e-9:
            by_time[f.time].append(f)
    times = sorted(by_time)
    if len(times) < 4:
        return 0.0, {}
    horizon = max(2, min(horizon_frames, len(times) // 3))
    start = times[-1 - horizon]
    targets = times[-target_times:]
    dev = model.aabb.device
    background = torch.tensor(scene.background, device=dev)
    images = {
        t: [(f.camera.to(dev), load_image(f, scene.background).to(dev)) for f in by_time[t]] for t in targets
    }
    sh_degree = model.cfg.sh_degree
    displacement = model.max_displacement(start)
    scores: dict[float, float] = {}
    for fraction in FREEZE_FRACTIONS:
        threshold = fraction * extent
        moving = (
            displacement > threshold if threshold > 0 else torch.ones_like(displacement, dtype=torch.bool)
        )
        errors = []
        for t in targets:
            state = model._physics_from(start, t, moving=moving)
            for camera, gt in images[t]:
                pred = model.render(state, camera, sh_degree, background).image.clamp(0, 1)
                errors.append(float(mse(pred, gt)))
        scores[threshold] = mae_psnr(errors)
    best = max(scores, key=lambda k: (round(scores[k], 2), -k))
    return best, scores
