"""Motion kinds: TRACE with its identified models against DefGS, per scene and per part.

For each synthetic scene trained both ways (`tracegs train --method trace` and `--method defgs`,
`cpu-fast`), one row per moving part: the scene's extrapolation MAE-PSNR (whole images) for both, the
part's own PSNR (its ground-truth mask) over the extrapolation and the interpolation splits for both,
TRACE's mean future path error of the part's Gaussians in percent of the scene size (the diagonal of
the ground-truth surface's bounding box), and which models the run's calibration adopted (`tracegs
calibrate`'s report: joint, free and thrown parts with their equations). Each run is scored once into
``RUN/eval_kinds.json`` (reused while newer than the run's checkpoint and post-training state).

Usage: .venv/bin/python benchmarks/motion_kinds.py --runs runs/trace/rolling ... --defgs runs/defgs/rolling ...
           [--json docs/results/motion-kinds.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from tracegs.eval.physics import _gt
from tracegs.eval.protocol import evaluate_run
from tracegs.results import make_record, write_record
from tracegs.run import load_config, load_extrapolation, run_data

COLUMNS = [
    "scene",
    "part",
    "trace_extrap",
    "defgs_extrap",
    "trace_part_extrap",
    "defgs_part_extrap",
    "trace_part_interp",
    "defgs_part_interp",
    "path_error_pct",
    "adopted",
]
NOTES = (
    "MAE-PSNR of whole images over the extrapolation split, PSNR of each moving part's ground-truth "
    "mask over the extrapolation and interpolation splits, and the part's mean future path error in "
    "percent of the scene size. `adopted`: the models the calibration adopted in the scene (joint, "
    "free or thrown part, with its equations); none: the learned physics everywhere."
)


def scores(run: Path) -> dict:
    """``tracegs eval`` of ``run``, cached in ``RUN/eval_kinds.json``."""
    path = Path(run) / "eval_kinds.json"
    inputs = [
        Path(run) / name for name in ("checkpoint.pt", "extrapolation.pt") if (Path(run) / name).is_file()
    ]
    if path.is_file() and all(path.stat().st_mtime >= p.stat().st_mtime for p in inputs):
        return json.loads(path.read_text())
    result = evaluate_run(run, with_lpips=False, save_images=False)
    path.write_text(json.dumps(result, indent=2))
    return result


def adopted(run: Path) -> str:
    """The models the run's calibration adopted, one ``kind: equations`` each; "none" without any."""
    state = load_extrapolation(run)
    found = []
    for entry in (state.report.get("joint_laws") or []) if state is not None else []:
        if entry.get("adopted") and isinstance(entry.get("model"), list):
            found.append(f"{entry.get('joint')}: {'; '.join(entry['model'])}")
        elif entry.get("adopted"):
            found.append(f"{entry.get('model', entry.get('joint'))}: {entry.get('why')}")
    for entry in (state.report.get("free_bodies") or []) if state is not None else []:
        if entry.get("chosen") or entry.get("adopted"):
            found.append("free body")
    return " | ".join(found) or "none"


def scene_size(data: Path) -> float:
    points = _gt(data)[0]
    return float(np.linalg.norm(points.max(0) - points.min(0)))


def _part(split: dict, name: str) -> float | None:
    value = (split.get("per_part") or {}).get(name, {}).get("psnr")
    return None if value is None else round(value, 2)


def rows_of(trace_run: Path, defgs_run: Path) -> list[dict]:
    """One row per moving part of the scene both runs were trained on."""
    trace, defgs = scores(trace_run), scores(defgs_run)
    data = run_data(load_config(Path(trace_run) / "config.json"))
    size = scene_size(data)
    names = [n for n in (trace["interpolation"].get("per_part") or {}) if n != "background"]
    physics = (trace.get("physics") or {}).get("parts", {})
    models = adopted(trace_run)
    rows = []
    for k, name in enumerate(names, start=1):
        error = physics.get(str(k), {}).get("mean_trajectory_error")
        if error is None or k == 1:  # part 1 of every scene is its still stand
            continue
        rows.append(
            {
                "scene": trace_run.name,
                "part": name,
                "trace_extrap": round(trace["extrapolation"]["mae_psnr"], 2),
                "defgs_extrap": round(defgs["extrapolation"]["mae_psnr"], 2),
                "trace_part_extrap": _part(trace["extrapolation"], name),
                "defgs_part_extrap": _part(defgs["extrapolation"], name),
                "trace_part_interp": _part(trace["interpolation"], name),
                "defgs_part_interp": _part(defgs["interpolation"], name),
                "path_error_pct": round(100 * error / size, 2),
                "adopted": models,
            }
        )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="trained TRACE run folders")
    ap.add_argument("--defgs", type=Path, nargs="+", required=True, help="DefGS runs of the same scenes")
    ap.add_argument("--json", type=Path, help="write the record here (docs/results/motion-kinds.json)")
    args = ap.parse_args()
    if len(args.runs) != len(args.defgs):
        ap.error("give one DefGS run per TRACE run, in the same order")
    rows = [r for t, d in zip(args.runs, args.defgs, strict=True) for r in rows_of(t, d)]
    for r in rows:
        print("  ".join(f"{k}={r[k]}" for k in COLUMNS))
    if args.json is not None:
        command = (
            "benchmarks/motion_kinds.py --runs "
            + " ".join(str(r) for r in args.runs)
            + " --defgs "
            + " ".join(str(r) for r in args.defgs)
        )
        title = "Motion kinds: identified models against DefGS, per scene and part (`cpu-fast`)"
        write_record(args.json, make_record("motion-kinds", rows, command, title, COLUMNS, NOTES))


if __name__ == "__main__":
    main()
