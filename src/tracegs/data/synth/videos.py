"""A synthetic scene as a rig's recordings: one MP4 per camera, and the cameras' true poses, for the
closed loop of ``tracegs import`` (videos in, cameras recovered, compared with the truth).

C: cameras, T: frames
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..frames import SPLITS


def _camera_frames(scene: Path) -> tuple[dict[int, list[tuple[int, Path]]], dict[int, np.ndarray]]:
    """Per camera id: its (frame id, image) over every split, and its OpenGL camera-to-world."""
    frames: dict[int, list[tuple[int, Path]]] = {}
    poses: dict[int, np.ndarray] = {}
    for split in SPLITS:
        path = scene / f"transforms_{split}.json"
        if not path.is_file():
            continue
        for f in json.loads(path.read_text())["frames"]:
            frames.setdefault(f["camera_id"], []).append((f["frame_id"], scene / f["file_path"]))
            poses[f["camera_id"]] = np.asarray(f["transform_matrix"], dtype=np.float64)
    return frames, poses


def camera_name(camera_id: int) -> str:
    return f"c{camera_id:02d}"


def write_rig_videos(scene: Path, out: Path, fps: float = 30.0) -> list[Path]:
    """One MP4 per camera of the ``tracegs synth`` folder ``scene`` under ``out`` (``c00.mp4``, ...),
    its frames in order over every split, composited on black where an image is transparent."""
    import imageio.v3 as iio

    from ..video import write_video

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for camera, items in sorted(_camera_frames(Path(scene))[0].items()):
        images = []
        for _, path in sorted(items):
            rgba = iio.imread(path).astype(np.float32) / 255
            rgb = rgba[..., :3] * rgba[..., 3:] if rgba.shape[-1] == 4 else rgba
            images.append(np.round(rgb * 255).astype(np.uint8))
        paths.append(write_video(out / f"{camera_name(camera)}.mp4", images, fps))
    return paths


def true_w2c(scene: Path) -> dict[str, np.ndarray]:
    """Per camera name (``camera_name``): its OpenCV world-to-camera [4, 4] in the synthetic scene."""
    poses = {}
    for camera, c2w in sorted(_camera_frames(Path(scene))[1].items()):
        c2w = c2w.copy()
        c2w[:3, 1:3] *= -1  # OpenGL -> OpenCV camera axes
        poses[camera_name(camera)] = np.linalg.inv(c2w)
    return poses


def imported_w2c(scene: Path) -> dict[str, np.ndarray]:
    """Per camera name: the OpenCV world-to-camera [4, 4] that ``tracegs import`` wrote to ``scene``."""
    poses = {}
    for split in SPLITS:
        path = Path(scene) / f"transforms_{split}.json"
        if path.is_file():
            for f in json.loads(path.read_text())["frames"]:
                c2w = np.asarray(f["transform_matrix"], dtype=np.float64)
                c2w[:3, 1:3] *= -1
                poses[f["camera"]] = np.linalg.inv(c2w)
    return poses


def closed_loop(scene: Path, work: Path, **import_args) -> dict:
    """The closed loop on the ``tracegs synth`` folder ``scene`` (rendered with textured surroundings):
    its cameras as videos under ``work/videos``, imported without their poses into ``work/imported``
    (``import_scene`` with ``import_args``), the recovered cameras aligned to the true ones by a
    similarity (``calibration.align_cameras``). Returns the alignment's errors and the import's report."""
    from ..calibration import align_cameras
    from ..importer import import_scene

    work = Path(work)
    write_rig_videos(Path(scene), work / "videos")
    report = import_scene(
        work / "imported", videos=work / "videos", **({"log": lambda s: None} | import_args)
    )
    truth, found = true_w2c(Path(scene)), imported_w2c(work / "imported")
    names = sorted(found)
    errors = align_cameras(np.stack([found[n] for n in names]), np.stack([truth[n] for n in names]))
    return errors | {"cameras": len(truth), "registered": len(names), "report": report}
