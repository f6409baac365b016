"""A real multi-view capture: CMU Panoptic `basketball` with the `capture` preset, TRACE and DefGS.

For each run (trained with `tracegs train --preset capture --downscale 2 --t-train-end 0.75`, the
method in its config): the 4 test cameras over the training span, the test cameras over the next 10
frames, and all cameras over the whole future, through `tracegs eval`'s protocol (`evaluate_run`);
a figure of the test cameras at one training time (render over ground truth) per run in
docs/figures/panoptic/; with --json, the record.

Usage: .venv/bin/python benchmarks/panoptic.py TRACE_RUN DEFGS_RUN [RUN=LABEL ...] [--json docs/results/panoptic.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tracegs.data.dataset import frame_interval
from tracegs.data.frames import load_image
from tracegs.data.scene import load_scene
from tracegs.eval.protocol import evaluate_run
from tracegs.results import make_record, sentences, write_record
from tracegs.run import load_run

NEXT = 10  # frames of the short future scored on the test cameras
COLUMNS = ["method", "split", "frames", "psnr", "mae_psnr", "ssim", "train s", "steps", "gaussians"]
NOTES = (
    "27 training and 4 test cameras x 150 frames, trained on frames 0-111 with no point cloud: the "
    "Gaussians start on the visual hull of the first frame's masks and on the surroundings the cameras see."
)


def record_notes(note: str = "") -> str:
    """The record's notes: :data:`NOTES`, then ``note`` (``--note``: the one caveat of these runs, e.g.
    how the rows' methods differ); ValueError if ``note`` is more than one sentence."""
    if len(sentences(note)) > 1:
        raise ValueError(f"--note must be one sentence (the notes have at most two), got {note!r}")
    return f"{NOTES} {note}".strip()


def scores(run: Path, label: str | None = None) -> tuple[list[dict], dict]:
    """The rows of one run (``label``: its method's name, else TRACE or DefGS) and its summary facts;
    the evaluations are kept in RUN/panoptic_eval.json while the checkpoint is older."""
    cache = run / "panoptic_eval.json"
    if cache.is_file() and cache.stat().st_mtime > (run / "checkpoint.pt").stat().st_mtime:
        full, soon = json.loads(cache.read_text())
    else:
        full, soon = _evaluations(run)
        cache.write_text(json.dumps([full, soon]))
    method = label or ("TRACE" if full["method"] == "trace" else "DefGS")
    new = "new_cameras"
    interp = full["interpolation"]
    rows = [
        {"method": method, "split": "test cameras, training span (t <= 0.75)", **_cells(interp)},
        {
            "method": method,
            "split": f"test cameras, next {NEXT} frames",
            **_cells(soon["extrapolation"]["per_cameras"][new]),
        },  # fmt: skip
        {
            "method": method,
            "split": "test cameras, whole future (t > 0.75)",
            **_cells(full["extrapolation"]["per_cameras"][new]),
        },  # fmt: skip
        {
            "method": method,
            "split": "training cameras, whole future",
            **_cells(full["extrapolation"]["per_cameras"]["train_cameras"]),
        },  # fmt: skip
    ]
    facts = {
        "train_seconds": full["train_seconds"],
        "gaussians": full["gaussians"],
        "iterations": full["iterations"],
    }
    return rows, facts


def _evaluations(run: Path) -> tuple[dict, dict]:
    """`evaluate_run` over the whole protocol, and over the next ``NEXT`` frames only."""
    full = evaluate_run(run, with_lpips=False, save_images=False)
    train = load_scene(full["scene"], "train")
    dt = frame_interval([f.time for f in train.frames], train.fps)
    last = max(f.time for f in train.frames if f.time <= full["t_train_end"] + 1e-9)
    return full, evaluate_run(run, with_lpips=False, save_images=False, horizon_end=last + NEXT * dt)


def _cells(s: dict) -> dict:
    return {
        "frames": s["frames"],
        "psnr": round(s["psnr"], 2),
        "mae_psnr": round(s["mae_psnr"], 2),
        "ssim": round(s["ssim"], 3),
    }


def figure(run: Path, out: Path, t: float) -> Path:
    """The test cameras at time ``t``: renders over ground truth."""
    loaded = load_run(run, "cpu")
    cfg = loaded.config
    test = load_scene(cfg.data, "test", cfg.downscale)
    frames = [f for f in test.frames if abs(f.time - t) < 1e-6]
    predictor = loaded.predictor.with_background(test.background)
    top = [predictor.render(f.camera, t).numpy() for f in frames]
    bottom = [load_image(f, test.background).numpy() for f in frames]
    grid = np.concatenate([np.concatenate(top, 1), np.concatenate(bottom, 1)], 0)
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, (grid.clip(0, 1) * 255).round().astype(np.uint8))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", help="run folders, each RUN or RUN=LABEL (the rows' method name)")
    ap.add_argument("--json", type=Path, help="write the results record here (docs/results/panoptic.json)")
    ap.add_argument("--figures", type=Path, default=Path("docs/figures/panoptic"))
    ap.add_argument(
        "--note",
        default="",
        help="the notes' second sentence: the one caveat (e.g. how the rows' methods differ)",
    )
    args = ap.parse_args()
    try:
        notes = record_notes(args.note)
    except ValueError as err:
        ap.error(str(err))
    rows = []
    for spec in args.runs:
        path, _, label = spec.partition("=")
        run = Path(path)
        r, facts = scores(run, label or None)
        run_facts = {
            "train s": round(facts["train_seconds"]),
            "steps": facts["iterations"],
            "gaussians": facts["gaussians"],
        }
        rows += [{**row, **run_facts} for row in r]
        name = r[0]["method"]
        if not label:
            figure(run, args.figures / f"{name.lower()}_test_cameras.png", 56 / 149)
    for row in rows:
        print("  ".join(str(row[c]) for c in COLUMNS))
    if args.json:
        command = "tracegs train --data ../shared/data/panoptic/basketball --run RUN --preset capture --downscale 2 --t-train-end 0.75 [--method defgs] && python benchmarks/panoptic.py RUN_TRACE RUN_DEFGS"  # fmt: skip
        record = make_record(
            "panoptic",
            rows,
            command + f" --json {args.json}",
            title="A real multi-view capture: CMU Panoptic `basketball` at 320x180 px (`capture` preset)",
            columns=COLUMNS,
            notes=notes,
        )
        write_record(args.json, record)


if __name__ == "__main__":
    main()
