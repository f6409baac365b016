"""The closed loop of ``tracegs import`` on a synthetic rig, where the truth is known: a ``tracegs synth``
scene rendered with textured surroundings, encoded as one MP4 per camera, imported without its poses
(COLMAP), the recovered cameras aligned to the true ones by a similarity (Umeyama). Prints the centre
errors as a fraction of the rig's radius and the viewing-direction errors in degrees, against the
targets (1% of the radius, 0.5 degrees).

Usage: .venv/bin/python benchmarks/import_closed_loop.py [--scene fan] [--resolution 480] [--views 12]
    [--frames 10] [--spp 8] [--camera-model SIMPLE_RADIAL] [--calib-frames 1] [--out runs/import_loop] [--json F]
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

from tracegs.data.synth import synthesize
from tracegs.data.synth.videos import closed_loop

CENTRE_TARGET, DIRECTION_TARGET = 0.01, 0.5


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--scene", default="fan")
    parser.add_argument("--resolution", type=int, default=480)
    parser.add_argument("--views", type=int, default=12)
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL")
    parser.add_argument("--calib-frames", type=int, default=1)
    parser.add_argument("--out", type=Path, default=Path("runs/import_loop"))
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    scene = args.out / f"{args.scene}_{args.resolution}_{args.views}x{args.frames}"
    started = time.perf_counter()
    if not (scene / "gt" / "synth.json").is_file():
        synthesize(
            args.scene,
            scene,
            args.resolution,
            args.views,
            args.frames,
            spp=args.spp,
            textured_surroundings=True,
        )
    rendered = time.perf_counter()
    work = args.out / "loop"
    shutil.rmtree(work, ignore_errors=True)
    result = closed_loop(scene, work, camera_model=args.camera_model, calib_frames=args.calib_frames)
    report = result.pop("report")
    row = {
        "scene": args.scene,
        "resolution": args.resolution,
        "cameras": result["cameras"],
        "registered": result["registered"],
        **error_cells(result, report),
        "camera_model": args.camera_model,
        "calib_frames": args.calib_frames,
        "undistortion": report["undistortion"],
        "render_s": round(rendered - started, 1),
        "import_s": round(time.perf_counter() - rendered, 1),
    }
    ok = (
        row["registered"] == row["cameras"]
        and row["centre_error_max_of_radius"] <= CENTRE_TARGET
        and row["direction_error_max_deg"] <= DIRECTION_TARGET
    )
    summarise(row, f"{args.scene} at {args.resolution} px", "the rig's radius", ok, args.json)


def error_cells(errors: dict, report: dict) -> dict:
    """The row cells of an import's ``report`` and its alignment's ``errors`` (``align_cameras``)."""
    return {
        "reprojection_error_px": report["calibration"].get("mean_reprojection_error_px"),
        "points": report["calibration"].get("points"),
        "centre_error_max_of_radius": errors["centre_error_max"],
        "centre_error_mean_of_radius": errors["centre_error_mean"],
        "direction_error_max_deg": errors["direction_error_max_deg"],
        "direction_error_mean_deg": errors["direction_error_mean_deg"],
    }


def summarise(row: dict, rig: str, radius: str, ok: bool, path: Path | None) -> None:
    """Print an import's camera errors (``row``: the benchmarks' keys) against the targets, and write
    ``row`` with the verdict to ``path`` when given."""
    print(
        f"{rig}: {row['registered']}/{row['cameras']} cameras registered, "
        f"reprojection error {row['reprojection_error_px']:.2f} px, import {row['import_s']:.0f} s\n"
        f"centres: {100 * row['centre_error_max_of_radius']:.2f}% of {radius} at most "
        f"(mean {100 * row['centre_error_mean_of_radius']:.2f}%)\n"
        f"directions: {row['direction_error_max_deg']:.3f} degrees at most "
        f"(mean {row['direction_error_mean_deg']:.3f})\n"
        f"{'within' if ok else 'NOT within'} the targets"
    )
    if path:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(row | {"within_targets": ok}, indent=2) + "\n")


if __name__ == "__main__":
    main()
