"""``tracegs import`` on a real rig: CMU Panoptic basketball's 31 cameras written as 31 videos, its
calibration dropped, imported with COLMAP, the recovered cameras aligned to the shipped calibration by
a similarity (Umeyama). Prints how many cameras registered and the centre errors as a fraction of the
dome's radius (target: every camera, within 2%), and the viewing-direction errors in degrees.

The imported scene (``OUT/imported``) is then trained like the shipped layout for the comparison of the
test cameras over the training span (``benchmarks/panoptic.py --data OUT/imported``).

Usage: .venv/bin/python benchmarks/import_panoptic.py [--data ../shared/data/panoptic/basketball]
    [--out runs/import_panoptic] [--camera-model SIMPLE_RADIAL] [--calib-frames 1] [--json F]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
from import_closed_loop import error_cells, summarise

from tracegs.data.calibration import align_cameras, read_calibration
from tracegs.data.importer import import_scene
from tracegs.data.synth.videos import imported_w2c
from tracegs.data.video import write_video

TEST_CAMERAS = ("0", "10", "15", "30")
CENTRE_TARGET = 0.02
FPS = 30.0


def write_videos(data: Path, out: Path) -> list[str]:
    """One MP4 per camera folder of ``data/ims`` (named by the folder), its JPEG frames in name order."""
    import imageio.v3 as iio

    out.mkdir(parents=True, exist_ok=True)
    names = sorted((p.name for p in (data / "ims").iterdir() if p.is_dir()), key=int)
    for name in names:
        target = out / f"{name}.mp4"
        if not target.is_file():
            frames = [iio.imread(p) for p in sorted((data / "ims" / name).glob("*.jpg"))]
            write_video(target, frames, FPS)
    return names


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("../shared/data/panoptic/basketball"))
    parser.add_argument("--out", type=Path, default=Path("runs/import_panoptic"))
    parser.add_argument("--camera-model", default="SIMPLE_RADIAL")
    parser.add_argument("--calib-frames", type=int, default=1)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    started = time.perf_counter()
    names = write_videos(args.data, args.out / "videos")
    written = time.perf_counter()
    report = import_scene(
        args.out / "imported",
        videos=args.out / "videos",
        camera_model=args.camera_model,
        calib_frames=args.calib_frames,
        test_cameras=TEST_CAMERAS,
        drop_unregistered=True,
        log=lambda s: None,
    )
    imported = time.perf_counter()
    found = imported_w2c(args.out / "imported")
    shipped = read_calibration(args.data, names).cameras
    kept = sorted(found, key=int)
    errors = align_cameras(np.stack([found[n] for n in kept]), np.stack([shipped[n].w2c for n in kept]))
    row = {
        "cameras": len(names),
        "registered": len(kept),
        "dropped": report["dropped"],
        "dome_radius": errors["rig_radius"],
        **error_cells(errors, report),
        "camera_model": args.camera_model,
        "calib_frames": args.calib_frames,
        "videos_s": round(written - started, 1),
        "import_s": round(imported - written, 1),
    }
    ok = row["registered"] == row["cameras"] and row["centre_error_max_of_radius"] <= CENTRE_TARGET
    summarise(row, "Panoptic basketball", "the dome's radius", ok, args.json)


if __name__ == "__main__":
    main()
