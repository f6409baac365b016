"""A real multi-view capture: CMU Panoptic `basketball` with the `capture` preset, TRACE, DefGS and Hold.

For each run (trained with `tracegs train --preset capture --downscale 2 --t-train-end 0.75`, the
method in its config): the 4 test cameras over the training span, the test cameras over the next 10
frames, and all cameras over the whole future, through `tracegs eval`'s protocol (`evaluate_run`),
on whole images and on the pixels that move (`moving_psnr`, the moving-region MAE-PSNR; "-" where
no frame had a moving mask); a figure of the test cameras at one training time (render over ground
truth) per run in docs/figures/panoptic/; with --json, the record. Hold trains nothing: it is the
first TRACE run scored with the motion `hold` (its Gaussians at the training span's end held still).

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
COLUMNS = [
    "method",
    "split",
    "frames",
    "psnr",
    "mae_psnr",
    "moving_psnr",
    "ssim",
    "train s",
    "steps",
    "gaussians",
]
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


def scores(run: Path, label: str | None = None, motion: str = "trace") -> tuple[list[dict], dict]:
    """The rows of one run scored with ``motion`` (``label``: its method's name, else TRACE, DefGS or,
    with the motion ``hold``, Hold) and its summary facts; the evaluations are kept in
    RUN/panoptic_eval.json (``panoptic_eval_hold.json``) while the checkpoint is older."""
    cache = run / ("panoptic_eval.json" if motion == "trace" else f"panoptic_eval_{motion}.json")
    if cache.is_file() and cache.stat().st_mtime > (run / "checkpoint.pt").stat().st_mtime:
        full, soon = json.loads(cache.read_text())
    else:
        full, soon = _evaluations(run, motion)
        cache.write_text(json.dumps([full, soon]))
    method = label or ("Hold" if motion == "hold" else "TRACE" if full["method"] == "trace" else "DefGS")
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
        "method": full["method"],
        "train_seconds": full["train_seconds"],
        "gaussians": full["gaussians"],
        "iterations": full["iterations"],
    }
    return rows, facts


def _evaluations(run: Path, motion: str = "trace") -> tuple[dict, dict]:
    """`evaluate_run` with ``motion`` over the whole protocol, and over the next ``NEXT`` frames only."""
    full = evaluate_run(run, with_lpips=False, save_images=False, motion=motion)
    train = load_scene(full["scene"], "train")
    dt = frame_interval([f.time for f in train.frames], train.fps)
    last = max(f.time for f in train.frames if f.time <= full["t_train_end"] + 1e-9)
    soon = evaluate_run(run, with_lpips=False, save_images=False, horizon_end=last + NEXT * dt, motion=motion)
    return full, soon


def _cells(s: dict) -> dict:
    moving = s.get("moving", {}).get("mae_psnr")
    return {
        "frames": s["frames"],
        "psnr": round(s["psnr"], 2),
        "mae_psnr": round(s["mae_psnr"], 2),
        "moving_psnr": "-" if moving is None else round(moving, 2),
        "ssim": round(s["ssim"], 3),
    }


def hold_rows(runs: list[tuple[Path, dict]]) -> list[dict]:
    """The Hold rows: the first TRACE run of ``runs`` ((run, its facts) pairs) scored with the motion
    ``hold``, with that run's facts (no training of its own); none without a TRACE run."""
    trace = next((run for run, facts in runs if facts["method"] == "trace"), None)
    if trace is None:
        return []
    rows, facts = scores(trace, motion="hold")
    return [{**row, **_run_facts(facts)} for row in rows]


def _run_facts(facts: dict) -> dict:
    return {
        "train s": round(facts["train_seconds"]),
        "steps": facts["iterations"],
        "gaussians": facts["gaussians"],
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
    rows, runs = [], []
    for spec in args.runs:
        path, _, label = spec.partition("=")
        run = Path(path)
        r, facts = scores(run, label or None)
        rows += [{**row, **_run_facts(facts)} for row in r]
        runs.append((run, facts))
        name = r[0]["method"]
        if not label:
            figure(run, args.figures / f"{name.lower()}_test_cameras.png", 56 / 149)
    rows += hold_rows(runs)
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
