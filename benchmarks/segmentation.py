"""Motion segmentation of trained runs against the scenes' ground-truth masks (the paper's Table 3
protocol: AP, PQ, F1, precision, recall at IoU 0.5, mIoU), at the training times and the future ones.

For each run folder: TRACE's physics features with K given (the count of ground-truth segments once
parts that move alike are merged, the static group included) and with --auto-k, and the DefGS
scene-flow baseline (f_defo's displacements) with K given, all through `tracegs segment`. Writes a
figure per scene (docs/figures/segmentation/<scene>.png: rendered image with the segments over it,
predicted mask, ground truth, at the last training time and at t = 1) and, with --json, the record.

Usage: .venv/bin/python benchmarks/segmentation.py RUN [RUN ...] [--json docs/results/segmentation.json]
(runs of `tracegs train --preset cpu-fast` or `tracegs bench methods`, e.g. runs/bench/runs/fan_TRACE_cpu-fast)
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tracegs.results import make_record, write_record
from tracegs.run import load_config
from tracegs.segment import SegmentConfig, segment_run
from tracegs.segment.truth import merged_parts

PAPER = {"ap": 95.82, "pq": 93.28, "f1": 97.90, "precision": 96.21, "recall": 99.86, "miou": 79.55}
METRICS = ("ap", "pq", "f1", "precision", "recall", "miou")


def true_k(data: Path) -> int:
    """Segments of the ground truth (static parts and parts moving alike merged), background excluded."""
    segment_of, _ = merged_parts(data / "gt" / "motion.json")
    if not segment_of:
        raise SystemExit(f"{data}: no gt/motion.json, so K is not known; run `tracegs segment --k K`")
    return len(set(segment_of.values()))


def rows_of(scene: str, method: str, k_mode: str, report: dict) -> list[dict]:
    rows = []
    for when in ("training_times", "future_times"):
        s = report["scores"][when]
        rows.append(
            {"scene": scene, "method": method, "K": f"{report['k']} ({k_mode})", "times": when.split("_")[0],
             "images": s["images"], **{m: round(100 * s[m], 2) for m in METRICS}}
        )  # fmt: skip
    return rows


def figure(run: Path, out: Path, t_last: float) -> Path:
    """The mask strips at the last training time and at t = 1 side by side."""
    strips = [iio.imread(run / "segment" / f"masks_t{t:.3f}.png") for t in (t_last, 1.0)]
    height = max(s.shape[0] for s in strips)
    strips = [np.pad(s, ((0, height - s.shape[0]), (0, 8), (0, 0)), constant_values=255) for s in strips]
    out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(out, np.concatenate(strips, axis=1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument(
        "--json", type=Path, help="write the results record here (docs/results/segmentation.json)"
    )
    ap.add_argument("--figures", type=Path, default=Path("docs/figures/segmentation"))
    args = ap.parse_args()
    rows, seconds, notes = [], [], []
    for run in args.runs:
        cfg = load_config(run / "config.json")
        data = Path(cfg.data)
        scene = data.name.split("_")[0]
        k = true_k(data)
        flow = SegmentConfig(features="flow")
        segment_run(run, time_=1.0, k=k, score=False)  # the future strip of the figure
        started = time.perf_counter()
        given = segment_run(run, k=k)
        seconds.append(time.perf_counter() - started)
        auto = segment_run(run, auto_k=True, out=run / "segment-auto")
        baseline = segment_run(run, k=k, settings=flow)
        rows += rows_of(scene, "TRACE", "given", given)
        rows += rows_of(scene, "TRACE", "auto", auto)
        rows += rows_of(scene, "DefGS flow", "given", baseline)
        figure(run, args.figures / f"{scene}.png", given["time"])
        merged = given["ground_truth"]["merged"]
        notes.append(
            f"{scene}: K = {k}" + (f" ({'; '.join(', '.join(g) for g in merged)} merged)" if merged else "")
            + f", auto-K {auto['k']}; segment {given['seconds']['segment']:.1f} s, scoring {given['seconds']['score']:.0f} s"
        )  # fmt: skip
    print(f"{'scene':<13}{'method':<12}{'K':<11}{'times':<10}" + "".join(f"{m:>10}" for m in METRICS))
    for r in rows:
        print(
            f"{r['scene']:<13}{r['method']:<12}{r['K']:<11}{r['times']:<10}"
            + "".join(f"{r[m]:10.2f}" for m in METRICS)
        )
    if args.json:
        columns = ["scene", "method", "K", "times", "images", *METRICS]
        paper = {"scene": "paper, TRACE on Dynamic Indoor", "method": "TRACE", "K": "given", "times": "all",
                 "images": 7200, **PAPER}  # fmt: skip
        record = make_record(
            "segmentation",
            [*rows, paper],
            "python benchmarks/segmentation.py "
            + " ".join(str(r) for r in args.runs)
            + f" --json {args.json}",
            title="Motion segmentation (the paper's Table 3 protocol)",
            columns=columns,
            notes=(
                "Runs of `tracegs train --preset cpu-fast` (seed 0) on the five 128 px scenes of `tracegs synth`. "
                "Every image of every split is scored (train: 12 cameras, val: 3 held-out cameras, both at "
                "t <= 0.763; the future: all 15 cameras at t > 0.763), each predicted segment against the ground "
                "truth's, the background one segment in both. The DefGS-flow baseline clusters the same runs' "
                "f_defo displacements over the training span (DefGS's field, trained here beside f_trd). "
                + " ".join(notes)
                + f" Times on {int(np.round(np.mean(seconds)))} s average for the scored `tracegs segment` call."
            ),
        )
        write_record(args.json, record)


if __name__ == "__main__":
    main()
