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
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from tracegs.data.scene import load_scene
from tracegs.results import make_record, sentences, write_record
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
COLUMNS = ["scene", "method", "K", *(f"{m} {tag}" for tag in ("train", "future") for m in SHOWN)]
COLUMNS += ["trained", "ground truth", "segment s", "score s"]
NOTES = (
    "Features are the paper's (the rigid motion fitted to f_trd's velocities of each Gaussian's 24 "
    "neighbours), K-means, then rounds in which each Gaussian joins the segment whose rigid motion explains "
    "its own (docs/SEGMENTATION.md)."
)
CAVEAT = (
    "Every masked image is scored, the background one segment; Panoptic's masks give foreground / "
    "background only."
)
"""The notes' second sentence unless ``--note`` gives another."""


def record_notes(note: str = "") -> str:
    """The record's notes: :data:`NOTES`, then ``note`` (``--note``: the one caveat a reader needs),
    :data:`CAVEAT` when it is empty; ValueError if ``note`` is more than one sentence."""
    if len(sentences(note)) > 1:
        raise ValueError(f"--note must be one sentence (the notes have at most two), got {note!r}")
    return f"{NOTES} {note or CAVEAT}"


def ground_truth(merged: list[list[str]]) -> str:
    """The ground truth's segments in a cell: its parts, and which were ``merged`` (moving alike)."""
    return "parts" + (f" ({'; '.join(', '.join(group) for group in merged)} merged)" if merged else "")


def rows_of(scene: str, method: str, k_mode: str, report: dict, **facts) -> list[dict]:
    """One row: the scores in percent at the training times and at the future times, the run's
    ``facts`` (how it was trained, the ground truth), the seconds to segment and to score."""
    row = {"scene": scene, "method": method, "K": f"{report['k']} ({k_mode})"}
    for when, tag in (("training_times", "train"), ("future_times", "future")):
        s = report["scores"][when]
        row.update({f"{m} {tag}": round(100 * s[m], 2) for m in SHOWN})
    seconds = report.get("seconds", {})
    row.update(facts)
    row.update({f"{k} s": round(seconds[k], 1) for k in ("segment", "score") if k in seconds})
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
    ap.add_argument("--note", default="", help="the notes' second sentence (default: the scoring's caveat)")
    args = ap.parse_args()
    try:
        notes = record_notes(args.note)
    except ValueError as err:
        ap.error(str(err))
    rows = []
    for run in args.runs:
        cfg = load_config(run / "config.json")
        data = Path(cfg.data)
        scene = scene_name(data)
        k = true_k(data)
        camera = load_scene(data, "train", cfg.downscale).frames[0].camera
        size = f"{camera.width}x{camera.height} px" if camera.width != camera.height else f"{camera.width} px"
        trained = f"`--preset {cfg.preset}`, {size}"
        flow = SegmentConfig(features="flow")
        if k is None:  # foreground masks only (Panoptic): K chosen, the flow baseline with the same K
            facts = {"trained": trained, "ground truth": "foreground / background"}
            given = segment_run(run, auto_k=True)
            rows += rows_of(scene, "TRACE", "auto", given, **facts)
            rows += rows_of(
                scene, "DefGS flow", "same", segment_run(run, k=given["k"], settings=flow), **facts
            )
            figure(run, args.figures / f"{scene}.png", given["time"], [given["time"]])
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
        given = segment_run(run, k=k)  # last: the run's stored labels are TRACE's with K given
        facts = {"trained": trained, "ground truth": ground_truth(given["ground_truth"]["merged"])}
        rows += rows_of(scene, "TRACE", "given", given, **facts)
        rows += rows_of(scene, "TRACE", "auto", auto, **facts)
        rows += rows_of(scene, "TRACE, K-means alone", "given", kmeans, **facts)
        rows += rows_of(scene, "DefGS flow", "given", baseline, **facts)
        rows += rows_of(scene, "DefGS flow, K-means alone", "given", flow_kmeans, **facts)
        figure(run, args.figures / f"{scene}.png", given["time"], [given["time"], 1.0])
    print("  ".join(COLUMNS))
    for r in rows:
        print("  ".join(str(r.get(c, "")) for c in COLUMNS))
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
            columns=COLUMNS,
            notes=notes,
        )
        write_record(args.json, record)


if __name__ == "__main__":
    main()
