"""The record of `tracegs import` (docs/results/import.json): how well it recovers a rig's cameras, and
what training on the recovered cameras costs against training on the true (or shipped) ones.

Rows:
* a synthetic rig (`--loop-scene SCENE IMPORTED`: a `tracegs synth --textured-surroundings` scene and
  its import from the MP4s of `synth/videos.py`): cameras registered, centre and direction errors
  after a similarity alignment; with `--loop-runs TRUE IMPORTED` the same training (`cpu-fast`) on the
  scene rendered without the surroundings (`tracegs synth`, same rig) and on its copy posed by the
  import (`--posed-copy`), extrapolation and interpolation MAE-PSNR through `tracegs eval`;
* Panoptic basketball (`--panoptic`: `benchmarks/import_panoptic.py`'s json): the same errors against
  the shipped calibration; with `--panoptic-runs SHIPPED IMPORTED` (`capture` trainings on the shipped
  layout and on the imported scene) PSNR on the test cameras over the training span.

Usage: .venv/bin/python benchmarks/import_record.py [--loop-scene SCENE IMPORTED] [--loop-runs TRUE IMPORTED]
    [--panoptic F.json] [--panoptic-runs SHIPPED IMPORTED] [--json OUT]
       .venv/bin/python benchmarks/import_record.py --posed-copy PLAIN IMPORTED OUT
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from tracegs.data.calibration import align_cameras
from tracegs.data.synth.videos import camera_name, imported_w2c, true_w2c
from tracegs.eval.protocol import evaluate_run
from tracegs.results import make_record, write_record

COLUMNS = [
    "rig", "cameras", "registered", "centre_max_pct", "centre_mean_pct", "direction_max_deg",
    "direction_mean_deg", "metric", "true_poses", "imported",
]  # fmt: skip


NOTES = (
    "Camera errors after the similarity that best aligns the imported centres with the true ones "
    "(percent of the rig's radius); trainings on the true and the imported calibration with the "
    "same flags, scored by `tracegs eval` on each scene's own held-out frames."
)


def _errors(row: dict, errors: dict, cameras: int, registered: int) -> dict:
    return row | {
        "cameras": cameras,
        "registered": registered,
        "centre_max_pct": round(100 * errors["centre_error_max"], 2),
        "centre_mean_pct": round(100 * errors["centre_error_mean"], 2),
        "direction_max_deg": round(errors["direction_error_max_deg"], 3),
        "direction_mean_deg": round(errors["direction_error_mean_deg"], 3),
    }


def _evaluation(run: Path) -> dict:
    """``tracegs eval`` of ``run`` without LPIPS and images, kept in RUN/import_eval.json."""
    cache = run / "import_eval.json"
    if cache.is_file() and cache.stat().st_mtime > (run / "checkpoint.pt").stat().st_mtime:
        return json.loads(cache.read_text())
    result = evaluate_run(run, with_lpips=False, save_images=False)
    cache.write_text(json.dumps(result))
    return result


def posed_copy(scene: Path, imported: Path, out: Path) -> Path:
    """The `tracegs synth` scene ``scene`` with each camera's pose and intrinsics those ``tracegs import``
    recovered for it (``imported``, the same rig's import, in its own frame), its images linked: the
    same training on the true and on the recovered cameras, on the scene's own images (an import
    trains on its decoded video frames, which a synthetic scene with textured surroundings makes hard
    for a preset built for objects). Its ``gt/`` is left out: it is in the true frame."""
    cameras = {}
    for split in ("train", "val", "test"):
        path = imported / f"transforms_{split}.json"
        if path.is_file():
            for f in json.loads(path.read_text())["frames"]:
                cameras[f["camera"]] = {
                    k: f[k] for k in ("transform_matrix", "fl_x", "fl_y", "cx", "cy", "w", "h")
                }
    out.mkdir(parents=True, exist_ok=True)
    for split in ("train", "val", "test"):
        data = json.loads((scene / f"transforms_{split}.json").read_text())
        frames = [f | cameras[camera_name(f["camera_id"])] for f in data["frames"]]
        top = {k: v for k, v in data.items() if k not in ("frames", "aabb", "camera_angle_x")}
        (out / f"transforms_{split}.json").write_text(json.dumps(top | {"frames": frames}, indent=1))
        if not (out / split).exists():
            (out / split).symlink_to((scene / split).resolve())
    return out


def loop_rows(scene: Path, imported: Path, runs: list[Path] | None) -> list[dict]:
    truth, found = true_w2c(scene), imported_w2c(imported)
    names = sorted(found)
    errors = align_cameras(np.stack([found[n] for n in names]), np.stack([truth[n] for n in names]))
    report = json.loads((imported / "import.json").read_text())
    rig = f"{scene.name} (synthetic, {report['timing']['size'][0]} px, {report['calibration'].get('camera_model')})"
    base = _errors({"rig": rig}, errors, len(truth), len(names))
    if not runs:
        return [base]
    true_eval, imported_eval = (_evaluation(r) for r in runs)
    return [
        base | {"metric": f"{split} MAE-PSNR", "true_poses": round(true_eval[split]["mae_psnr"], 2),
                "imported": round(imported_eval[split]["mae_psnr"], 2)}
        for split in ("extrapolation", "interpolation")
    ]  # fmt: skip


def panoptic_rows(found: dict, runs: list[Path] | None) -> list[dict]:
    base = _errors(
        {"rig": "Panoptic basketball (31 videos, 640x360)"},
        {
            "centre_error_max": found["centre_error_max_of_radius"],
            "centre_error_mean": found["centre_error_mean_of_radius"],
            "direction_error_max_deg": found["direction_error_max_deg"],
            "direction_error_mean_deg": found["direction_error_mean_deg"],
        },
        found["cameras"],
        found["registered"],
    )
    if not runs:
        return [base]
    shipped, imported = (_evaluation(r)["interpolation"] for r in runs)
    return [
        base | {"metric": "test cameras, training span: PSNR", "true_poses": round(shipped["psnr"], 2),
                "imported": round(imported["psnr"], 2)}
    ]  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--loop-scene", type=Path, nargs=2, metavar=("SCENE", "IMPORTED"))
    ap.add_argument("--loop-runs", type=Path, nargs=2, metavar=("TRUE", "IMPORTED"))
    ap.add_argument("--panoptic", type=Path, help="benchmarks/import_panoptic.py's json")
    ap.add_argument("--panoptic-runs", type=Path, nargs=2, metavar=("SHIPPED", "IMPORTED"))
    ap.add_argument(
        "--posed-copy",
        type=Path,
        nargs=3,
        metavar=("PLAIN", "IMPORTED", "OUT"),
        help="write OUT: the synth scene PLAIN on the cameras of IMPORTED (posed_copy), and stop",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.posed_copy:
        print(posed_copy(*args.posed_copy))
        return
    rows = []
    if args.loop_scene:
        rows += loop_rows(*args.loop_scene, args.loop_runs)
    if args.panoptic:
        rows += panoptic_rows(json.loads(args.panoptic.read_text()), args.panoptic_runs)
    for r in rows:
        print("  ".join(f"{k}={r.get(k)}" for k in COLUMNS))
    if args.json is not None:
        command = "benchmarks/import_record.py " + " ".join(
            f"--{k.replace('_', '-')} " + (" ".join(map(str, v)) if isinstance(v, list) else str(v))
            for k, v in vars(args).items()
            if v is not None and k != "json"
        )
        write_record(args.json, make_record("import", rows, command, columns=COLUMNS, notes=NOTES))


if __name__ == "__main__":
    main()
