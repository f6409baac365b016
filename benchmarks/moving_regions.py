"""Where things move: trained runs scored on the pixels that move, TRACE beside Hold.

The whole-image PSNR of a synthetic scene is mostly its still background; this benchmark puts each
run's extrapolation MAE-PSNR on the moving parts' pixels (``tracegs eval``'s ``moving`` entry:
the scene's ground-truth masks of its moving parts, dilated) beside the whole image, for TRACE and for
Hold (the Gaussians of the last observed time held: ``tracegs eval --motion hold``, no training).
Each run is scored once per motion into ``RUN/eval_moving_<motion>.json`` (kept, and reused while it
is newer than the run's checkpoint).

Usage: .venv/bin/python benchmarks/moving_regions.py --runs runs/fan runs/slider ...
           [--json docs/results/moving-regions.json]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tracegs.eval.protocol import evaluate_run
from tracegs.results import make_record, write_record

COLUMNS = [
    "scene",
    "trace_extrap",
    "trace_extrap_moving",
    "hold_extrap_moving",
    "trace_interp",
    "trace_interp_moving",
    "moving_share",
]
NOTES = (
    "MAE-PSNR in dB over the extrapolation split (every camera after the training span) and the "
    "interpolation split, on whole images and on the moving parts' pixels (the ground-truth masks of "
    "the parts that move, dilated by 3 px; `moving_share` is their share of the extrapolation pixels). "
    "Hold renders f_defo's Gaussians at the last training time for every later time, from the same run."
)


def scores(run: Path, motion: str) -> dict:
    """``tracegs eval`` of ``run`` with ``motion``, cached in ``RUN/eval_moving_<motion>.json``."""
    path = Path(run) / f"eval_moving_{motion}.json"
    checkpoint = Path(run) / "checkpoint.pt"
    if path.is_file() and path.stat().st_mtime >= checkpoint.stat().st_mtime:
        return json.loads(path.read_text())
    result = evaluate_run(run, motion=motion, with_lpips=False, save_images=False)
    path.write_text(json.dumps(result, indent=2))
    return result


def _moving(split: dict) -> float | None:
    value = (split.get("moving") or {}).get("mae_psnr")
    return None if value is None else round(value, 2)


def row(scene: str, trace: dict, hold: dict) -> dict:
    """One scene's row from its TRACE and Hold evaluations."""
    extrap, interp = trace["extrapolation"], trace["interpolation"]
    share = (extrap.get("moving") or {}).get("pixel_share")
    return {
        "scene": scene,
        "trace_extrap": round(extrap["mae_psnr"], 2),
        "trace_extrap_moving": _moving(extrap),
        "hold_extrap_moving": _moving(hold["extrapolation"]),
        "trace_interp": round(interp["mae_psnr"], 2),
        "trace_interp_moving": _moving(interp),
        "moving_share": None if share is None else round(share, 4),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="trained TRACE run folders")
    ap.add_argument("--json", type=Path, help="write the record here (docs/results/moving-regions.json)")
    args = ap.parse_args()
    rows = [row(run.name, scores(run, "trace"), scores(run, "hold")) for run in args.runs]
    for r in rows:
        print("  ".join(f"{k}={r[k]}" for k in COLUMNS))
    if args.json is not None:
        command = "benchmarks/moving_regions.py --runs " + " ".join(str(r) for r in args.runs)
        title = "Where things move: extrapolation on the moving parts' pixels, TRACE and Hold (`cpu-fast`)"
        record = make_record("moving-regions", rows, command, title, COLUMNS, NOTES)
        write_record(args.json, record)


if __name__ == "__main__":
    main()
