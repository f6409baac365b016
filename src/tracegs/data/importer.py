"""``tracegs import``: a synchronised rig's recordings -> a calibrated scene in the Blender layout.

The steps: the recordings on one clock (``video.py``: one video per camera, or one folder of frames
per camera); the cameras calibrated by COLMAP on frames where the rig stands still (``colmap.py``),
or read from a calibration file (``calibration.py``); the images undistorted where the camera model
has distortion; the rig moved round the origin, up along +z, at a chosen size (``normalise``); the
motion masks of the static cameras (``motion_masks.py``) written beside the images, where the
``capture`` preset finds foreground masks. The scene::

    transforms_{train,val,test}.json   per frame: file_path, time, camera (its recording's name),
                                       camera_id, transform_matrix, fl_x, fl_y, cx, cy, w, h
    images/CAMERA/CAMERA_fNNNNN.png    the frames (undistorted)
    masks/images/CAMERA/...png         what moves in each frame (255), for cameras of >= 10 frames
    colmap/sparse/0                    the COLMAP model (of the recorded, distorted calibration frames)
    import.json                        the report: recordings, how they were reconciled, calibration

``train`` holds every camera not named by ``--val-cameras`` or ``--test-cameras``, at every time; the
held-out cameras' frames are ``val`` and ``test``. The scene is assembled in a temporary folder beside
``out`` and renamed into place at the end: a failure leaves nothing half-written.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from ..utils import fresh_folder, replace_folder
from .calibration import normalise, read_calibration, rescaled, transform_w2c
from .colmap import RigFit, calibrate_rig, largest_shift, undistort, undistortion_map
from .frames import DatasetError
from .video import Source, Timing, decode, find_sources, plan

REPORT = "import.json"
MIN_SHIFT_PX = 0.1
"""Distortion that moves no pixel by more than this is left in the images (undistorting would only
blur them)."""


def image_name(camera: str, k: int) -> str:
    """The frame ``k`` of ``camera`` under ``images/`` (the stem is unique in the scene)."""
    return f"{camera}/{camera}_f{k:05d}.png"


def _decode_all(sources: list[Source], timing: Timing, root: Path, log) -> None:
    import imageio.v3 as iio

    for c, source in enumerate(sources):
        (root / source.name).mkdir(parents=True)
        for k, image in decode(source, c, timing):
            iio.imwrite(root / image_name(source.name, k), image)
        log(f"{source.name}: {timing.count} frames from {source.path.name}")


def _calibrate(
    sources, timing, images: Path, work: Path, calibration, calib_frames, camera_model, log
) -> RigFit:
    names = [s.name for s in sources]
    if calibration is not None:
        fit = read_calibration(Path(calibration), names)
        fit.cameras = {n: rescaled(f, timing.width, timing.height) for n, f in fit.cameras.items()}
        return fit
    if calib_frames < 1:
        raise ValueError(f"--calib-frames must be >= 1, got {calib_frames}")
    ks = sorted({int(round(k)) for k in np.linspace(0, timing.count - 1, min(calib_frames, timing.count))})
    log(f"COLMAP: {len(names)} cameras x {len(ks)} frames ({camera_model})")
    fit = calibrate_rig(images, {n: [image_name(n, k) for k in ks] for n in names}, work, camera_model)
    fit.report |= {"model": "colmap/sparse/" + Path(fit.report["model"]).name, "frames": ks}
    return fit


def _undistort(fit: RigFit, sources: list[Source], timing: Timing, images: Path) -> dict:
    """Undistort every image of each camera whose model has distortion; returns per camera what was done."""
    import imageio.v3 as iio

    done = {}
    for name, camera in fit.cameras.items():
        if camera.distorted is None:
            done[name] = "pinhole model: kept"
            continue
        coords = undistortion_map(camera.distorted, camera.K, camera.width, camera.height)
        shift = largest_shift(coords)
        if shift < MIN_SHIFT_PX:
            done[name] = f"distortion under {MIN_SHIFT_PX} px ({shift:.3f}): kept"
            continue
        for k in range(timing.count):
            path = images / image_name(name, k)
            iio.imwrite(path, undistort(iio.imread(path), coords))
        done[name] = f"undistorted ({camera.distorted.model_name}, pixels moved up to {shift:.1f} px)"
    return done


def _frame(name: str, c: int, k: int, time: float, w2c: np.ndarray, fit) -> dict:
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes, as the Blender layout stores them
    K = fit.K
    return {
        "file_path": "images/" + image_name(name, k),
        "time": time,
        "camera": name,
        "camera_id": c,
        "frame_id": k,
        "transform_matrix": c2w.tolist(),
        "fl_x": float(K[0, 0]),
        "fl_y": float(K[1, 1]),
        "cx": float(K[0, 2]),
        "cy": float(K[1, 2]),
        "w": fit.width,
        "h": fit.height,
    }


def _splits(names: list[str], val: tuple[str, ...], test: tuple[str, ...], sources: list[Source]) -> dict:
    known = {s.name for s in sources}
    for flag, chosen in (("--val-cameras", val), ("--test-cameras", test)):
        for n in chosen:
            if n not in known:
                raise ValueError(f"{flag} {n}: no such camera (the cameras: {', '.join(sorted(known))})")
    if set(val) & set(test):
        raise ValueError(
            f"camera {sorted(set(val) & set(test))[0]} is named by both --val-cameras and --test-cameras"
        )
    held = set(val) | set(test)
    splits = {"train": [n for n in names if n not in held], "val": [n for n in names if n in val]}
    splits["test"] = [n for n in names if n in test]
    if not splits["train"]:
        raise ValueError("every camera is held out: leave at least one for training")
    return splits


def import_scene(
    out: Path,
    videos: Path | None = None,
    images: Path | None = None,
    fps: float | None = None,
    start: float = 0.0,
    end: float | None = None,
    offsets: tuple[float, ...] = (),
    downscale: int = 1,
    calibration: Path | None = None,
    calib_frames: int = 1,
    camera_model: str = "SIMPLE_RADIAL",
    scale: float | None = None,
    val_cameras: tuple[str, ...] = (),
    test_cameras: tuple[str, ...] = (),
    drop_unregistered: bool = False,
    log=print,
) -> dict:
    """Write the scene ``out`` from the recordings in ``videos`` (or ``images``) and return the report
    (the module docstring; each argument is the ``tracegs import`` flag of its name)."""
    sources = find_sources(videos, images, fps if images is not None else None)
    timing = plan(sources, fps if videos is not None else None, start, end, offsets, downscale)
    splits = _splits([s.name for s in sources], val_cameras, test_cameras, sources)
    for note in timing.notes:
        log(note)
    out = Path(out)
    tmp = fresh_folder(out, "tracegs import", REPORT)
    try:
        _decode_all(sources, timing, tmp / "images", log)
        fit = _calibrate(
            sources, timing, tmp / "images", tmp / "colmap", calibration, calib_frames, camera_model, log
        )
        (tmp / "colmap" / "database.db").unlink(missing_ok=True)
        dropped = dict(fit.unregistered)
        for source in sources:
            if source.name in dropped and not drop_unregistered:
                raise DatasetError(
                    f"{source.path}: camera {source.name} has no calibration ({dropped[source.name]}); "
                    "--drop-unregistered writes the scene without it"
                )
        kept = [s.name for s in sources if s.name in fit.cameras]
        if len(kept) < 2:
            raise DatasetError(
                f"{sources[0].path.parent}: fewer than two cameras calibrated ({', '.join(kept) or 'none'})"
            )
        for name in dropped:
            shutil.rmtree(tmp / "images" / name)
        undistorted = _undistort(fit, sources, timing, tmp / "images")
        w2c = np.stack([fit.cameras[n].w2c for n in kept])
        placed = {"kept": "as the calibration file gives it"}
        if calibration is None or scale is not None or fit.report.get("tool") == "COLMAP model":
            s, R, t, placed = normalise(w2c, 4.0 if scale is None else scale)
            w2c = transform_w2c(w2c, s, R, t)
        w2c_of = dict(zip(kept, w2c, strict=True))
        ids = {s.name: c for c, s in enumerate(sources)}
        written = {}
        for split, names in splits.items():
            names = [n for n in names if n in w2c_of]
            if not names:
                continue
            frames = [
                _frame(n, ids[n], k, t, w2c_of[n], fit.cameras[n])
                for k, t in enumerate(timing.times)
                for n in names
            ]
            top = {"fps": max(timing.count - 1, 1), "video_fps": timing.fps, "background": [0.0, 0.0, 0.0]}
            (tmp / f"transforms_{split}.json").write_text(
                json.dumps(top | {"frames": frames}, indent=1) + "\n"
            )
            written[split] = names
        mask_report = _masks(tmp, written)
        report = {
            "recordings": [
                {
                    "camera": s.name,
                    "file": str(s.path),
                    "fps": s.fps,
                    "frames": s.frames,
                    "size": [s.width, s.height],
                }
                for s in sources
            ],
            "timing": {
                "fps": timing.fps,
                "start_s": timing.start,
                "frames": timing.count,
                "offsets_s": dict(zip([s.name for s in sources], timing.offsets, strict=True)),
                "size": [timing.width, timing.height],
                "reconciled": timing.notes,
            },
            "calibration": fit.report | {"camera_model": camera_model if calibration is None else "given"},
            "registered": kept,
            "dropped": dropped,
            "undistortion": undistorted,
            "placement": placed,
            "splits": written,
            "masks": mask_report,
        }
        (tmp / REPORT).write_text(json.dumps(report, indent=2) + "\n")
        replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return report


def _masks(root: Path, splits: dict[str, list[str]]) -> dict:
    """The motion masks of every split (``masks/<image path>.png``), and per split how many."""
    from .motion_masks import write_motion_masks

    done = {}
    for split in splits:
        report = write_motion_masks(root, split, root / "masks")
        done[split] = {"written": report["written"], "cameras": report["cameras"]}
    return done


def format_report(report: dict) -> str:
    """The console lines of ``import_scene``'s report."""
    cal = report["calibration"]
    error = cal.get("mean_reprojection_error_px")
    lines = [
        f"{report['timing']['frames']} frames at {report['timing']['fps']:g} fps, "
        f"{report['timing']['size'][0]}x{report['timing']['size'][1]}",
        f"{len(report['registered'])} cameras calibrated ({cal.get('tool')})"
        + (f", mean reprojection error {error:.2f} px" if error is not None else ""),
        *(f"dropped {name}: {why}" for name, why in report["dropped"].items()),
        *report["timing"]["reconciled"],
        ", ".join(f"{split}: {len(n)} camera{'s' * (len(n) != 1)}" for split, n in report["splits"].items()),
    ]
    return "\n".join(lines)
