"""Continual learning (the paper's Section 4.4): observations keep arriving, the model keeps
predicting the next window.

Round 0 trains on [0, W] as ``tracegs train`` does; it then predicts (W, W + H] and is scored there.
Round k adds the frames up to W + k S and continues from round k - 1's model (its Gaussians, fields
and per-camera colours; fresh optimisers), never from scratch: ``fraction`` of the stage-2 steps,
no static stage, no densification, the whole observed span sampled from the first step, and no
Gaussian held static in training (what stood still so far may start to move). Each round is a run
folder of its own (``RUN/round_KK``: a checkpoint, its calibration, its scores), trained only on
frames up to its window's end (``t_train_end``): the training cameras' frames of every split
(``arriving_frames``: a scene whose train split ends early still has those cameras' later frames in
its test split). It is scored on every camera's frames in its predicted window. The table of rounds
is ``RUN/continual.json``.

Windows, horizons and strides are times in [0, 1] (the scene's span), or frame counts with
``frames``: "15 frames, then one more per round, predict the next 10" is ``window=15, step=1,
horizon=10`` in frames (a frame is one interval of the scene's times).
"""

from __future__ import annotations

import copy
import json
import time
from dataclasses import dataclass
from pathlib import Path

from .config import TrainConfig
from .data.dataset import frame_interval
from .data.scene import available_splits, load_scene
from .utils import atomic_write_text

CONTINUAL = "continual.json"


@dataclass
class Continual:
    """The rounds of a continual training (module docstring)."""

    window: float = 0.15
    """Observed span of the first round."""
    horizon: float = 0.15
    """Span predicted and scored after each round."""
    step: float | None = None
    """Span added per round (default: ``horizon``)."""
    frames: bool = False
    """``window``, ``horizon`` and ``step`` count frames instead of times."""
    fraction: float = 0.25
    """Fraction of the stage-2 steps that each round after the first trains."""


def round_ends(times: list[float], plan: Continual) -> list[tuple[float, float]]:
    """(observed until, predicted until) of each round over a scene's training ``times``: the first
    observes ``window``, each next one ``step`` more, while something is left to predict."""
    times = sorted(set(times))
    first, last = times[0], times[-1]
    unit = frame_interval(times, None) if plan.frames else 1.0
    window, horizon = plan.window * unit, plan.horizon * unit
    step = (plan.step if plan.step is not None else plan.horizon) * unit
    if not (window > 0 and horizon > 0 and step > 0):
        raise ValueError(f"window, horizon and step must be positive, got {window}, {horizon}, {step}")
    ends, end = [], first + window
    while end < last - 1e-9:
        ends.append((end, min(end + horizon, last)))
        end += step
    if not ends:
        raise ValueError(
            f"a window of {window:.4g} leaves nothing of the span {first:.4g}-{last:.4g} to predict"
        )
    return ends


def round_config(cfg: TrainConfig, k: int, observed_until: float, plan: Continual) -> TrainConfig:
    """The training config of round ``k``: ``cfg`` on [0, ``observed_until``] into ``RUN/round_KK``;
    from the second round on, the warm round's settings (module docstring)."""
    rc = copy.deepcopy(cfg)
    rc.run = Path(cfg.run) / f"round_{k:02d}"
    rc.t_train_end = observed_until
    rc.arriving_frames = True  # the training cameras' frames of every split, up to the window's end
    if k > 0:
        rc.static_iterations = 0
        rc.dynamic_iterations = max(1, round(plan.fraction * cfg.dynamic_iterations))
        rc.densify.refine_stop = 0
        rc.stage2.time_growth_fraction = 0.0
        rc.stage2.skip_static = False
        rc.stage2.static_outside_masks = False
    return rc


def train_continual(
    cfg: TrainConfig, plan: Continual, with_lpips: bool = True, progress: bool = True
) -> dict:
    """Train and score every round of ``plan`` on ``cfg.data`` into ``cfg.run`` (module docstring);
    the table (also ``RUN/continual.json``). A killed run resumes: finished rounds are read back."""
    from .eval.protocol import evaluate_run
    from .train.trainer import Trainer

    times = [
        f.time for s in available_splits(cfg.data) for f in load_scene(cfg.data, s, cfg.downscale).frames
    ]
    rounds, previous = [], None
    Path(cfg.run).mkdir(parents=True, exist_ok=True)
    for k, (observed, predicted) in enumerate(round_ends(times, plan)):
        rc = round_config(cfg, k, observed, plan)
        start = time.perf_counter()
        summary = Trainer(rc, progress=progress, warm_start=previous).train()
        train_s = time.perf_counter() - start
        scores = evaluate_run(rc.run, with_lpips=with_lpips, save_images=False, horizon_end=predicted)
        future = scores["extrapolation"]
        rounds.append(
            {
                "round": k,
                "observed_until": round(observed, 6),
                "extrapolated_until": round(predicted, 6),
                "frames": future.get("frames", 0),
                **{key: future[key] for key in ("psnr", "mae_psnr", "ssim", "lpips_vgg") if key in future},
                "steps": summary["iterations"],
                "wall_s": round(train_s, 1),
            }
        )
        previous = rc.run
        _write(cfg, plan, rounds)
    return _write(cfg, plan, rounds)


def _write(cfg: TrainConfig, plan: Continual, rounds: list[dict]) -> dict:
    keys = [k for k in ("psnr", "mae_psnr", "ssim", "lpips_vgg") if all(k in r for r in rounds)]
    table = {
        "scene": str(cfg.data),
        "method": cfg.method,
        "preset": cfg.preset,
        "plan": plan.__dict__,
        "rounds": rounds,
        "average": {k: sum(r[k] for r in rounds) / len(rounds) for k in keys},
        "wall_s": round(sum(r["wall_s"] for r in rounds), 1),
    }
    atomic_write_text(Path(cfg.run) / CONTINUAL, json.dumps(table, indent=2))
    return table
