"""Extrapolation where the forces are not constant: TRACE (`cpu-fast` as it ships, joint laws on), TRACE
with the paper's extrapolation (``extrapolation.joint_laws`` off) and DefGS on the five scenes of `tracegs synth` whose forces change
(pendulum, spring, brake, bounce, turntable), with the issue's targets beside the scores: the
extrapolation MAE-PSNR within 3 dB of the run's interpolation, at least DefGS + 5 dB, and the moving
parts' future trajectory error under 1% of the scene extent.

The runs are `tracegs bench methods` runs (trained, or reused where they exist, in OUT/runs; the
paper-extrapolation row reuses the TRACE training and is only calibrated and scored again).

With ``--scenes`` or ``--variants`` only those rows are measured again; the other rows of an
existing ``--json`` record are kept as they were, each with the commit and the machine it was measured
at (its columns; and its DefGS row still scores the new ones against DefGS).

Usage: .venv/bin/python benchmarks/nonconstant_forces.py [--out runs/bench] [--json docs/results/nonconstant-forces.json]
    [--scenes bounce turntable] [--variants TRACE "TRACE paper extrapolation"]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from tracegs.bench import METHODS, run_variant_table, scene_folder
from tracegs.data.cameras import scene_extent_from_cameras
from tracegs.data.scene import load_scene
from tracegs.results import current_commit, machine_description, make_record, read_record, write_record

SCENES = ("pendulum", "spring", "brake", "bounce", "turntable")
VARIANTS = ("TRACE", "TRACE paper extrapolation", "DefGS")
PRESET, RESOLUTION = "cpu-fast", 128
COLUMNS = ["commit", "machine", "scene", "variant", "interp_psnr", "extrap_psnr", "extrap_minus_interp",
           "extrap_minus_defgs", "traj_err_pct_extent", "meets_targets"]  # fmt: skip
NOTES = (
    "`cpu-fast`, 128 px, seed 0; MAE-PSNR dB, `traj_err_pct_extent` the moving parts' largest mean future "
    "trajectory error in % of the scene extent; targets: extrapolation >= interpolation - 3 dB, >= DefGS "
    "+ 5 dB, trajectory error < 1%. `TRACE` is `cpu-fast` with the joint laws (docs/PHYSICS.md), `TRACE "
    "paper extrapolation` the same training calibrated without them."
)
"""The record's notes; where each row was measured is in its ``commit`` and ``machine`` columns."""


def trajectory_error(run: Path, extent: float) -> float | None:
    """The largest mean future trajectory error of a moving part (eval.json's per-part physics), as a
    percentage of the scene extent; None when the run's eval has no per-part physics."""
    parts = json.loads((run / "eval.json").read_text()).get("physics", {}).get("parts", {})
    errors = [p["mean_trajectory_error"] for p in parts.values() if "mean_trajectory_error" in p]
    return round(100 * max(errors) / extent, 3) if errors else None


def kept_rows(record: dict) -> dict[tuple[str, str], dict]:
    """The rows of an existing ``record`` by (scene, variant), each with the commit and the machine it was
    measured at: its own, else the record's (a row without a machine of another commit: None)."""
    kept = {}
    for row in record["rows"]:
        commit = row.get("commit", record["commit"])
        machine = row.get("machine") or (record["machine"] if commit == record["commit"] else None)
        kept[(row["scene"], row["variant"])] = {**row, "commit": commit, "machine": machine}
    return kept


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("runs/bench"))
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--report-only", action="store_true", help="train nothing; tabulate finished runs")
    parser.add_argument("--scenes", nargs="+", default=list(SCENES), choices=SCENES)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    a = parser.parse_args()
    variants = {k: METHODS[k] for k in a.variants}
    rows = run_variant_table(
        "nonconstant-forces", variants, a.out, tuple(a.scenes), PRESET, RESOLUTION, train=not a.report_only
    )
    kept = {}  # the rows of the existing record not measured again
    if a.json is not None and a.json.exists():
        kept = kept_rows(read_record(a.json))
    by_scene: dict[str, dict[str, dict]] = {}
    for row in rows:
        by_scene.setdefault(row["scene"], {})[row["variant"]] = row
        kept.pop((row["scene"], row["variant"]), None)
    table = []
    for scene, found in by_scene.items():
        data = scene_folder(a.out, scene, RESOLUTION, synthesize_missing=False)
        cams = torch.stack([f.camera.center for f in load_scene(data, "train").frames])
        extent = scene_extent_from_cameras(cams)
        defgs = found.get("DefGS", kept.get((scene, "DefGS"), {})).get("extrap_psnr")
        for variant, row in found.items():
            run = a.out / "runs" / f"{scene}_{variant.replace(' ', '_')}_{PRESET}"
            interp, extrap = row["interp_psnr"], row["extrap_psnr"]
            traj = trajectory_error(run, extent)
            table.append(
                {
                    "scene": scene,
                    "variant": variant,
                    "interp_psnr": round(interp, 2),
                    "extrap_psnr": round(extrap, 2),
                    "extrap_minus_interp": round(extrap - interp, 2),
                    "extrap_minus_defgs": None if defgs is None else round(extrap - defgs, 2),
                    "traj_err_pct_extent": traj,
                    "meets_targets": variant != "DefGS"
                    and defgs is not None
                    and traj is not None
                    and extrap >= interp - 3
                    and extrap >= defgs + 5
                    and traj < 1.0,
                    "commit": current_commit(),
                    "machine": machine_description(),
                }
            )
    order = {(s, v): i for i, (s, v) in enumerate((s, v) for s in SCENES for v in VARIANTS)}
    table = sorted([*table, *kept.values()], key=lambda r: order.get((r["scene"], r["variant"]), len(order)))
    print(json.dumps(table, indent=2))
    if a.json is not None and table:
        command = f".venv/bin/python benchmarks/nonconstant_forces.py --json {a.json}"
        title = "Forces that are not constant (`cpu-fast`, 128 px)"
        record = make_record("nonconstant-forces", table, command, title=title, columns=COLUMNS, notes=NOTES)
        write_record(a.json, record)


if __name__ == "__main__":
    main()
