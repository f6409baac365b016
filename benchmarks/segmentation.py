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
import json
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tracegs.data.scene import load_scene
from tracegs.results import make_record, write_record
from tracegs.run import load_config
from tracegs.segment import SegmentConfig, segment_run
from tracegs.segment.truth import merged_parts

PAPER = {"ap": 95.82, "pq": 93.28, "f1": 97.90, "precision": 96.21, "recall": 99.86, "miou": 79.55}


def true_k(data: Path) -> int | None:
    """Segments of the ground truth (static parts and parts moving alike merged), background excluded;
    None without gt/motion.json (a capture with foreground masks only: then K is chosen, --auto-k)."""
    segment_of, _ = merged_parts(data / "gt" / "motion.json")
    return len(set(segment_of.values())) if segment_of else None


def scene_name(data: Path) -> str:
    """The scene's name as its generator wrote it (``scene`` in transforms_train.json), else the folder's."""
    meta = data / "transforms_train.json"
    name = json.loads(meta.read_text()).get("scene") if meta.is_file() else None
    return name or data.name.split("_")[0]


SHOWN = ("ap", "pq", "f1", "miou")


def rows_of(scene: str, method: str, k_mode: str, report: dict) -> list[dict]:
    """One row: the scores in percent at the training times and at the future times."""
    row = {"scene": scene, "method": method, "K": f"{report['k']} ({k_mode})"}
    for when, tag in (("training_times", "train"), ("future_times", "future")):
        s = report["scores"][when]
        row.update({f"{m} {tag}": round(100 * s[m], 2) for m in SHOWN})
    return [row]


def figure(run: Path, out: Path, t_last: float, times: list[float]) -> Path:
    """The mask strips at ``times`` (the last training time, t = 1) side by side."""
    strips = [iio.imread(run / "segment" / f"masks_t{t:.3f}.png") for t in times]
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
    ap.add_argument(
        "--note", default="", help="a sentence added to the record's notes (e.g. where the runs differ)"
    )
    args = ap.parse_args()
    rows, seconds, notes = [], [], []
    for run in args.runs:
        cfg = load_config(run / "config.json")
        data = Path(cfg.data)
        scene = scene_name(data)
        k = true_k(data)
        camera = load_scene(data, "train", cfg.downscale).frames[0].camera
        size = f"{camera.width}x{camera.height} px" if camera.width != camera.height else f"{camera.width} px"
        trained = f"`--preset {cfg.preset}`, {size}"
        flow = SegmentConfig(features="flow")
        started = time.perf_counter()
        if k is None:  # foreground masks only (Panoptic): K chosen, the flow baseline with the same K
            given = segment_run(run, auto_k=True)
            seconds.append(time.perf_counter() - started)
            rows += rows_of(scene, "TRACE", "auto", given)
            rows += rows_of(scene, "DefGS flow", "same", segment_run(run, k=given["k"], settings=flow))
            figure(run, args.figures / f"{scene}.png", given["time"], [given["time"]])
            notes.append(f"{scene} ({trained}): foreground / background only, auto-K {given['k']}.")
            continue
        segment_run(run, time_=1.0, k=k, score=False)  # the future strip of the figure
        auto = segment_run(run, auto_k=True, out=run / "segment-auto")
        kmeans = segment_run(
            run, k=k, settings=SegmentConfig(refine_iterations=0), out=run / "segment-kmeans"
        )
        baseline = segment_run(run, k=k, settings=flow)
        flow_kmeans = segment_run(
            run,
            k=k,
            settings=SegmentConfig(features="flow", refine_iterations=0),
            out=run / "segment-flow-kmeans",
        )
        started = time.perf_counter()
        given = segment_run(run, k=k)  # last: the run's stored labels are TRACE's with K given
        seconds.append(time.perf_counter() - started)
        rows += rows_of(scene, "TRACE", "given", given)
        rows += rows_of(scene, "TRACE", "auto", auto)
        rows += rows_of(scene, "TRACE, K-means alone", "given", kmeans)
        rows += rows_of(scene, "DefGS flow", "given", baseline)
        rows += rows_of(scene, "DefGS flow, K-means alone", "given", flow_kmeans)
        figure(run, args.figures / f"{scene}.png", given["time"], [given["time"], 1.0])
        merged = given["ground_truth"]["merged"]
        notes.append(
            f"{scene} ({trained}): K = {k}" + (f" ({'; '.join(', '.join(g) for g in merged)} merged)" if merged else "")
            + f", auto-K {auto['k']}; segment {given['seconds']['segment']:.1f} s, scoring {given['seconds']['score']:.0f} s."
        )  # fmt: skip
    columns = ["scene", "method", "K", *(f"{m} {tag}" for tag in ("train", "future") for m in SHOWN)]
    print("  ".join(columns))
    for r in rows:
        print("  ".join(str(r[c]) for c in columns))
    if args.json:
        paper = {"scene": "paper: Dynamic Indoor, all 7200 images", "method": "TRACE", "K": "given",
                 **{f"{m} train": PAPER[m] for m in SHOWN}, **{f"{m} future": "" for m in SHOWN}}  # fmt: skip
        record = make_record(
            "segmentation",
            [*rows, paper],
            "python benchmarks/segmentation.py "
            + " ".join(str(r) for r in args.runs)
            + f" --json {args.json}",
            title="Motion segmentation (the paper's Table 3 protocol)",
            columns=columns,
            notes=(
                "Runs of `tracegs train` (seed 0) on scenes of `tracegs synth` and, where given, CMU Panoptic "
                "basketball (`--t-train-end 0.75`); each scene's preset and image size are in its sentence below. "
                "Every image with a mask is "
                "scored: on the synthetic scenes train (12 cameras) and val (3 held-out cameras) at t <= 0.763, "
                "the future all 15 cameras at t > 0.763; each predicted segment against the ground truth's, the "
                "background one segment in both, no segment ignored (`--ignore-pixels 0`). Features: the paper's "
                "(|v_bar|, v_bar, |w|, w/|w|) of the rigid motion fitted to f_trd's particle velocities of each "
                "Gaussian's 24 nearest neighbours (`--settings.twist-neighbours`), K-means, then three rounds in "
                "which each Gaussian joins the segment whose rigid motion over the span best explains its own "
                "(docs/SEGMENTATION.md, step 4; started from K-means on the weighted features and on each feature "
                "group alone, the partition of lowest rigid cost kept; `TRACE, K-means alone`: K-means on the "
                "weighted features, no refinement). The runs mark static "
                "Gaussians with a margin of 5 spacings round what moves (`stage2.static_margin`). The DefGS-flow "
                "baseline clusters the same runs' f_defo displacements over the training span (DefGS's field, "
                "trained here beside f_trd), refined the same way from its one group (`DefGS flow, K-means alone`: without); with one moving part all find it. Panoptic: its seg/ masks are foreground "
                "/ background of the training cameras, so only that is scored (not the paper's per-player "
                "protocol). "
                + " ".join(notes)
                + (f" {args.note}" if args.note else "")
                + " Precision and recall of every row: each run's segment.json."
                + f" `tracegs segment` with its scoring took {np.mean(seconds):.0f} s per run on average."
            ),
        )
        write_record(args.json, record)


if __name__ == "__main__":
    main()
