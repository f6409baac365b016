"""Scoring a run's segmentation against a scene's ground-truth masks, per time and pooled, at the
training times (t <= the run's t_max) and the future ones: every split of the scene whose frames have
masks, each frame rendered at its own time and camera.
"""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

from ..data.scene import available_splits, load_scene
from ..extrapolate import Predictor
from .metrics import match_image, pool
from .truth import GroundTruth


def foreground(label_image: np.ndarray, static_label: int | None) -> np.ndarray:
    """[H, W] 1 where a moving segment is rendered, else 0 (the background and the static group)."""
    fg = label_image > 0
    if static_label is not None:
        fg &= label_image != static_label + 1
    return fg.astype(np.int64)


@torch.no_grad()
def score_segmentation(predictor: Predictor, labels: torch.Tensor, k: int, has_static: bool, data: Path,
                       downscale: int, truth: GroundTruth, splits: list[str] | None = None,
                       ignore_pixels: int = 0) -> dict:  # fmt: skip
    """``{"splits": {split: scores}, "training_times": scores, "future_times": scores, "per_time": [...]}``
    where scores are ``metrics.Scores.as_dict()``; frames without a mask are skipped. ``ignore_pixels``:
    ground-truth segments smaller than this are left out (``metrics.match_image``)."""
    matches: dict[tuple[str, float], list] = defaultdict(list)
    dev = predictor.device
    for split in splits or available_splits(data):
        by_time = defaultdict(list)
        for frame in load_scene(data, split, downscale).frames:
            if truth.mask_path(frame).is_file():
                by_time[frame.time].append(frame)
        for t, frames in sorted(by_time.items()):
            gaussians = predictor.gaussians_at(t)
            for frame in frames:
                pred, confidence = predictor.render_labels(
                    frame.camera.to(dev), labels, k, gaussians=gaussians
                )
                gt = truth.read(frame)
                if truth.layout == "foreground":
                    pred = foreground(pred, 0 if has_static else None)
                matches[(split, t)].append(match_image(gt, pred, confidence, ignore_pixels))
    t_max = predictor.t_max
    by_split, by_time_all = defaultdict(list), defaultdict(list)
    for (split, t), ms in matches.items():
        by_split[split] += ms
        by_time_all[t] += ms
    past = [m for t, ms in by_time_all.items() if t <= t_max + 1e-9 for m in ms]
    future = [m for t, ms in by_time_all.items() if t > t_max + 1e-9 for m in ms]
    return {
        "splits": {split: pool(ms).as_dict() for split, ms in by_split.items()},
        "training_times": pool(past).as_dict(),
        "future_times": pool(future).as_dict(),
        "per_time": [{"time": t, **pool(ms).as_dict()} for t, ms in sorted(by_time_all.items())],
    }
