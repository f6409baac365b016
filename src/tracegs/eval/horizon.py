"""Long horizons: a trained run's future rendered far past its data (the paper's long-horizon figure),
scored per time while there is ground truth, and a plain statement of where nothing was checked.

Three spans, each later one less supported: up to ``t_max`` the training images (and the backtests of
the free bodies and joint laws, which end there); up to the last ground-truth time the scores; past it
only the renders, and how much of what moves stays in sight (the share of the Gaussians the fields
move, all of them without a static mask, whose centres stay inside the box of their positions at
``t_max``, padded by half its size): a prediction that flies apart shows as a falling share long
before anyone looks at the images. A prediction that scatters in place (a person's Gaussians drifting
apart into a cloud) shows as a growing ``spread``: the median distance of those Gaussians to their
nearest neighbours, as a multiple of its value at ``t_max`` (``spread``).
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..data.dataset import frame_interval
from ..data.frames import load_image
from ..data.scene import available_splits, load_scene
from ..models.gaussians import nearest_neighbours
from ..run import load_run, run_data
from ..utils import atomic_write_image
from .metrics import mae_psnr, mse


def long_horizon(
    run: Path,
    until: float,
    data: Path | None = None,
    cameras: int = 4,
    device: str = "auto",
    out: Path | None = None,
) -> dict:
    """Render the first ``cameras`` cameras that training never used (else the training cameras) of
    ``run`` at every frame time from its ``t_max`` to ``until`` into ``out`` (default
    ``RUN/eval/horizon``), with PSNR where the scene has an image of that camera at that time (module
    docstring); the per-time table and the times up to which anything was checked."""
    run = Path(run)
    out = run / "eval" / "horizon" if out is None else Path(out)
    loaded = load_run(run, device, data)
    predictor, cfg = loaded.predictor, loaded.config
    data = run_data(cfg, data)  # (a clear error when the scene is not there)
    dev = predictor.device
    t_max = float(loaded.meta["t_max"])
    splits = {s: load_scene(data, s, cfg.downscale) for s in available_splits(data)}
    train = splits["train"]
    dt = frame_interval([f.time for f in train.frames], train.fps)
    trained = {f.camera_id for f in train.frames}
    new = [f for s, sc in splits.items() if s != "train" for f in sc.frames if f.camera_id not in trained]
    pool = new or train.frames
    ids = list(dict.fromkeys(f.camera_id for f in pool))[:cameras]
    views = {c: next(f for f in pool if f.camera_id == c) for c in ids}
    truth = {(f.camera_id, round(f.time, 6)): f for f in pool}
    end_of_truth = max((f.time for f in pool), default=t_max)
    moving = predictor.model.moving_rows  # the Gaussians the fields move (a capture's room stands still)
    at_max = _moving(predictor.gaussians_at(t_max)["means"], moving)
    lo, hi = at_max.min(0).values, at_max.max(0).values
    pad = 0.5 * (hi - lo)
    sample = _sample(at_max.shape[0])
    spacing = spread(at_max, sample)
    rows, k = [], 1
    while t_max + k * dt <= until + 0.01 * dt:
        t = t_max + k * dt
        g = predictor.gaussians_at(t)
        means = _moving(g["means"], moving)
        inside = ((means >= lo - pad) & (means <= hi + pad)).all(-1).float().mean()
        row = {"t": round(t, 6), "in_sight": round(float(inside), 4)}
        row["spread"] = round(spread(means, sample) / spacing, 4) if spacing > 0 else None
        scores = []
        for c, f in views.items():
            image = predictor.render(f.camera.to(dev), gaussians=g, camera_id=f.camera_id)
            atomic_write_image(out / f"c{c}_t{t:.4f}.png", image)
            gt = truth.get((c, round(t, 6)))
            if gt is not None:
                scores.append(float(mse(image, load_image(gt, train.background).to(dev))))
        if scores:
            row["psnr"] = round(mae_psnr(scores), 3)  # (the per-time PSNR of ``tracegs eval``)
        rows.append(row)
        k += 1
    return {
        "run": str(run),
        "trained_until": t_max,
        "checked_until": end_of_truth,
        "rendered_until": rows[-1]["t"] if rows else t_max,
        "cameras": ids,
        "per_time": rows,
        "images": str(out),
        "note": (
            f"fitted and backtested up to t = {t_max:.4g}; scored against images up to t = "
            f"{end_of_truth:.4g}; past that, renders only: nothing checks them"
        ),
    }


SPREAD_NEIGHBOURS, SPREAD_SAMPLE = 4, 4096
"""``spread`` looks at the ``SPREAD_NEIGHBOURS`` nearest neighbours of at most ``SPREAD_SAMPLE``
Gaussians (a fixed sample of those the fields move, the same at every time)."""


def spread(means: torch.Tensor, sample: torch.Tensor) -> float:
    """The median over the Gaussians ``sample`` (indices into ``means`` [N, 3]) of their mean distance
    to their ``SPREAD_NEIGHBOURS`` nearest neighbours among ``means``: how far apart what moves lies.
    0 with fewer than two Gaussians."""
    if means.shape[0] < 2:
        return 0.0
    d2, _ = nearest_neighbours(means.float(), SPREAD_NEIGHBOURS, of=sample.to(means.device))
    return float(d2.sqrt().mean(-1).median())


def _sample(n: int) -> torch.Tensor:
    """At most ``SPREAD_SAMPLE`` of ``n`` indices, evenly spaced (the same at every time)."""
    return torch.linspace(0, n - 1, min(n, SPREAD_SAMPLE)).round().long().unique()


def _moving(means: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    return means if rows is None or len(rows) == 0 else means[rows.to(means.device)]
