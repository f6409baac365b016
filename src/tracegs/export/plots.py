"""Figures for reports: PSNR against future time for several runs, and GT | method image strips."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def horizon_plot(runs: dict[str, Path], out: Path, title: str = "") -> Path:
    """Per-time extrapolation PSNR of each run (label -> run folder with eval.json) as a PNG."""
    series = {}
    for label, run in runs.items():
        rows = json.loads((Path(run) / "eval.json").read_text())["extrapolation"]["per_time"]
        series[label] = ([r["t"] for r in rows], [r["psnr"] for r in rows])
    xlabel, ylabel = "time t (training ends before the first point)", "PSNR (dB, all cameras)"
    return line_plot(series, out, xlabel, ylabel, title or "Extrapolation quality against horizon")


def line_plot(series: dict[str, tuple[list, list]], out: Path, xlabel: str, ylabel: str, title: str) -> Path:
    """A PNG of one line per ``series`` entry (label -> (xs, ys))."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.2), dpi=120)
    for label, (xs, ys) in series.items():
        ax.plot(xs, ys, marker="o", ms=3, label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out)
    plt.close(fig)
    return out


def error_image(pred: np.ndarray, gt: np.ndarray, gain: float) -> np.ndarray:
    """Grey [H, W, 3] image of ``gain`` x the mean absolute RGB error, clipped to [0, 1]."""
    err = np.clip(gain * np.abs(pred[..., :3] - gt[..., :3]).mean(axis=-1), 0.0, 1.0)
    return np.repeat(err[..., None], 3, axis=-1)


def image_strip(
    data: Path,
    runs: dict[str, Path],
    out: Path,
    camera_id: int = 0,
    count: int = 4,
    error_gain: float = 0.0,
) -> Path:
    """Rows = GT and each run's rendering (from ``eval/extrapolation``), columns = future times.
    With ``error_gain`` > 0 each run's row is followed by its error map (:func:`error_image`)."""
    import imageio.v3 as iio

    from ..data.scene import load_image
    from ..eval.protocol import split_frames

    first = json.loads((Path(next(iter(runs.values()))) / "eval.json").read_text())
    frames = [
        f
        for f in split_frames(data, first["t_train_end"])["extrapolation"]
        if f.camera_id in (camera_id, None)
    ]
    frames = sorted(frames, key=lambda f: f.time)
    picks = [frames[round(k * (len(frames) - 1) / max(count - 1, 1))] for k in range(count)] if frames else []
    gt = [load_image(f).numpy() for f in picks]
    rows = [gt]
    for run in runs.values():
        rows.append(
            [
                iio.imread(Path(run) / "eval" / "extrapolation" / f"{f.name}.png")[..., :3] / 255.0
                for f in picks
            ]
        )
        if error_gain > 0:
            rows.append([error_image(p, g, error_gain) for p, g in zip(rows[-1], gt, strict=True)])
    grid = np.concatenate([np.concatenate(r, axis=1) for r in rows], axis=0)
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, (np.clip(grid, 0, 1) * 255 + 0.5).astype(np.uint8))
    return out
