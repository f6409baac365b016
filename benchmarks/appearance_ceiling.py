"""The frozen-appearance ceiling of synthetic scenes: the best extrapolation PSNR that a model moving
Gaussians of constant colour can reach there (``tracegs.data.synth.ceiling``; docs/RESULTS.md).

Usage: .venv/bin/python benchmarks/appearance_ceiling.py SCENE_FOLDER [...] [--json F] [--mean-frames N]
(SCENE_FOLDER: written by ``tracegs synth``, e.g. runs/bench/scenes/fan_128.)
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tracegs.data.synth.ceiling import appearance_ceiling
from tracegs.results import machine_description, make_record, write_record


def record_notes(mean_frames: int) -> str:
    """The record's notes: what the two bounds are (``mean_frames``: the training frames the mean
    bound averages) and what `lowest_part` names."""
    return (
        "The best extrapolation a model of constant-colour Gaussians can reach: each scene's extrapolation "
        "split rendered with the exact geometry and motion but each surface point's appearance frozen, at "
        f"the handover (`ceiling_handover`) or averaged over {mean_frames} training frames (`ceiling_mean`). "
        "`lowest_part` is the part with the lowest bound at the handover."
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folders", nargs="+", type=Path)
    parser.add_argument("--handover-frames", type=float, default=4.0, help="as extrapolation.handover_frames")
    parser.add_argument(
        "--mean-frames", type=int, default=12, help="training frames averaged by the mean bound"
    )
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    results = []
    for folder in args.folders:
        r = appearance_ceiling(folder, args.handover_frames, args.mean_frames) | {
            "machine": machine_description()
        }
        results.append(r)
        for mode in ("handover", "mean"):
            b = r[mode]
            parts = ", ".join(
                f"{k} {v['psnr'] or float('inf'):.1f} dB ({100 * v['error_share']:.0f}%)"
                for k, v in b["per_part"].items()
            )
            print(
                f"{r['scene']} ({mode}): {b['mae_psnr']:.2f} dB MAE-PSNR over {b['frames_scored']} frames; {parts}"
            )
    if args.json:
        rows = []
        for r in results:
            parts = r["handover"]["per_part"]
            lowest = min(parts, key=lambda k: parts[k]["psnr"] or float("inf"))
            rows.append(
                {
                    "scene": r["scene"],
                    "ceiling_handover": r["handover"]["mae_psnr"],
                    "ceiling_mean": r["mean"]["mae_psnr"],
                    "lowest_part": lowest,
                    "lowest_part_psnr": parts[lowest]["psnr"],
                }
            )
        folders = " ".join(str(f) for f in args.folders)
        command = f".venv/bin/python benchmarks/appearance_ceiling.py {folders} --json {args.json}"
        title = "Appearance ceiling: the best future PSNR of constant-colour Gaussians on exact motion"
        notes = record_notes(args.mean_frames)
        write_record(args.json, make_record("appearance-ceiling", rows, command, title=title, notes=notes))


if __name__ == "__main__":
    main()
