"""Parser for the Blender / D-NeRF / NVFi dataset format.

A scene folder holds ``transforms_{train,val,test}.json``. Each file has a list ``frames`` whose items
give ``file_path`` (relative to the json, with or without ``.png``), ``transform_matrix`` (camera-to-world,
OpenGL axes) and, for dynamic scenes, ``time`` in [0, 1]. Intrinsics come from ``camera_angle_x``
(and optionally ``camera_angle_y``) or ``fl_x``/``fl_y``/``cx``/``cy``, per frame or for the whole file.
Optional top-level fields written by ``tracegs synth``: ``fps``, ``t_train_end``, ``background``,
``aabb``, ``scene``. RGBA images are composited on the dataset's background colour (white unless the
file says otherwise, as the Blender datasets are evaluated).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch

from ..image_metrics import read_image_array
from .cameras import Camera, opengl_c2w_to_viewmat
from .frames import DatasetError, Frame, SceneSplit, fail, read_json

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


def _resolve_image(json_path: Path, file_path, index: int) -> Path:
    """The image a ``file_path`` names, inside the scene folder; without a suffix (D-NeRF writes
    ``./train/r_000``) the first of ``.png``, ``.jpg``, ``.jpeg`` that exists (``.png`` if none does, for
    the error message). An absolute path, or one that leaves the folder (``../x.png``), is an error: a
    scene file names images of its own scene only."""
    if not isinstance(file_path, str) or not file_path:
        raise fail(json_path, f"frame {index}: 'file_path' must be a non-empty string, got {file_path!r}")
    root = Path(os.path.normpath(json_path.parent.absolute()))
    if Path(file_path).is_absolute():
        raise fail(
            json_path, f"frame {index}: 'file_path' {file_path!r} is absolute; give it relative to {root}"
        )
    lexical = Path(os.path.normpath(root / file_path))
    if lexical != root and root not in lexical.parents:
        raise fail(json_path, f"frame {index}: 'file_path' {file_path!r} leaves the scene folder {root}")
    p = lexical  # not resolved: an image linked from elsewhere keeps its name in the scene
    if p.suffix.lower() in IMAGE_SUFFIXES:
        return p
    candidates = [p.with_name(p.name + suffix) for suffix in IMAGE_SUFFIXES[:3]]
    return next((c for c in candidates if c.is_file()), candidates[0])


def _image_size(json_path: Path, path: Path, index: int) -> tuple[int, int]:
    """Width and height of the image of frame ``index`` (read from its header)."""
    if not path.is_file():
        raise fail(json_path, f"frame {index}: image {path} not found")
    try:
        shape = read_image_array(path).shape
    except ValueError as e:
        raise DatasetError(str(e)) from None
    return int(shape[1]), int(shape[0])


def _number(json_path: Path, value, what: str, positive: bool = False) -> float:
    """``value`` as a finite float (positive with ``positive``); else a DatasetError saying ``what``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise fail(json_path, f"{what} must be a number, got {value!r}")
    value = float(value)
    if not math.isfinite(value) or (positive and value <= 0):
        raise fail(
            json_path, f"{what} must be a {'positive' if positive else 'finite'} number, got {value!r}"
        )
    return value


def _times(json_path: Path, entries: list[dict], split: str) -> list[float]:
    """The frames' times; a split without any ``time`` is a static scene (every frame at t = 0), one
    where only some frames have it is an error (a missing time would silently become t = 0)."""
    has_time = ["time" in e for e in entries]
    if not any(has_time):
        return [0.0] * len(entries)
    if not all(has_time):
        i = has_time.index(False)
        raise fail(json_path, f"frame {i}: no 'time' (the other frames of the split have one)")
    times = []
    for i, e in enumerate(entries):
        t = _number(json_path, e["time"], f"frame {i}: 'time'")
        if t < -1e-6 or (split == "train" and t > 1 + 1e-6):
            # the fields' time encodings assume the format's [0, 1]: at integer frame indices every
            # sin(2^k pi t) is 0 and all times look alike
            raise fail(
                json_path,
                f"frame {i}: 'time' {t:g} is outside [0, 1]; the Blender / D-NeRF format gives "
                "times normalised to [0, 1] (e.g. frame index / last frame index)",
            )
        times.append(t)
    return times


def _intrinsics(json_path: Path, entry: dict, top: dict, width: int, height: int, index: int) -> torch.Tensor:
    """Intrinsics from per-frame keys first, then the file's top-level keys."""

    def get(key, positive=True):
        value = entry.get(key, top.get(key))
        return None if value is None else _number(json_path, value, f"frame {index}: {key!r}", positive)

    fx, fy = get("fl_x"), get("fl_y")
    for key in ("camera_angle_x", "camera_angle_y"):
        angle = get(key)
        if angle is not None and angle >= math.pi:
            raise fail(
                json_path, f"frame {index}: {key!r} {angle:g} must be below pi (a field of view in radians)"
            )
    if fx is None and get("camera_angle_x") is not None:
        fx = 0.5 * width / math.tan(0.5 * get("camera_angle_x"))
    if fy is None and get("camera_angle_y") is not None:
        fy = 0.5 * height / math.tan(0.5 * get("camera_angle_y"))
    if fx is None:
        raise fail(json_path, f"frame {index}: no intrinsics (camera_angle_x or fl_x)")
    fy = fx if fy is None else fy
    cx = get("cx", positive=False)
    cy = get("cy", positive=False)
    cx = width / 2 if cx is None else cx
    cy = height / 2 if cy is None else cy
    return torch.tensor([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], dtype=torch.float32)


def _pose(json_path: Path, entry: dict, index: int) -> torch.Tensor:
    """The frame's camera-to-world matrix [4, 4]: finite, 4x4."""
    try:
        c2w = torch.as_tensor(np.asarray(entry["transform_matrix"], dtype=np.float64))
    except (ValueError, TypeError):
        c2w = None
    if c2w is None or c2w.shape != (4, 4) or not torch.isfinite(c2w).all():
        shape = "x".join(map(str, c2w.shape)) if c2w is not None else "not numeric"
        raise fail(json_path, f"frame {index}: 'transform_matrix' must be a finite 4x4 matrix (got {shape})")
    return c2w


def _size(json_path: Path, entry: dict, top: dict, index: int) -> tuple[int, int] | None:
    """The frame's ``w`` and ``h`` from the json (per frame or for the file), if it gives them."""
    w, h = entry.get("w", top.get("w")), entry.get("h", top.get("h"))
    if w is None or h is None:
        return None
    w, h = (_number(json_path, v, f"frame {index}: {k!r}", positive=True) for k, v in (("w", w), ("h", h)))
    if w != int(w) or h != int(h):
        raise fail(json_path, f"frame {index}: 'w' and 'h' must be whole numbers of pixels, got {w:g}, {h:g}")
    return int(w), int(h)


def _scene_facts(json_path: Path, top: dict) -> dict:
    """The optional top-level fields (``background``, ``fps``, ``t_train_end``, ``aabb``), checked."""
    facts = {}
    background = top.get("background", (1.0, 1.0, 1.0))
    if not isinstance(background, (list, tuple)) or len(background) != 3:
        raise fail(json_path, f"'background' must be 3 numbers (RGB in [0, 1]), got {background!r}")
    facts["background"] = tuple(_number(json_path, c, "'background'") for c in background)
    facts["fps"] = _number(json_path, top["fps"], "'fps'", positive=True) if "fps" in top else None
    t_end = top.get("t_train_end")
    if t_end is not None:
        t_end = _number(json_path, t_end, "'t_train_end'", positive=True)
        if t_end > 1:
            raise fail(json_path, f"'t_train_end' {t_end:g} is outside (0, 1]")
    facts["t_train_end"] = t_end
    aabb = top.get("aabb")
    if aabb is not None:
        try:
            aabb = torch.tensor(aabb, dtype=torch.float32)
        except (ValueError, TypeError):
            aabb = None
        if aabb is None or aabb.shape != (2, 3) or not torch.isfinite(aabb).all():
            raise fail(json_path, "'aabb' must be [[xmin, ymin, zmin], [xmax, ymax, zmax]], finite")
    facts["aabb"] = aabb
    return facts


def load_blender(root: str | Path, split: str = "train", downscale: int = 1) -> SceneSplit:
    """Parse ``root/transforms_{split}.json`` into frames with cameras (images are not read here).

    ``downscale`` divides the image size (and the intrinsics) by an integer factor; images are
    box-filtered to that size when loaded by :func:`load_image`.
    """
    root = Path(root)
    json_path = root / f"transforms_{split}.json"
    top = read_json(json_path)
    entries = top["frames"]
    for i, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise fail(json_path, f"frame {i} is not an object (got a {type(entry).__name__})")
        missing = [k for k in ("file_path", "transform_matrix") if k not in entry]
        if missing:
            raise fail(json_path, f"frame {i}: needs 'file_path' and 'transform_matrix' (no {missing[0]!r})")
    times = _times(json_path, entries, split)
    frames = []
    first_size: tuple[int, int] | None = None  # images of one file share a size unless w/h say otherwise
    for i, (entry, time) in enumerate(zip(entries, times, strict=True)):
        image_path = _resolve_image(json_path, entry["file_path"], i)
        c2w = _pose(json_path, entry, i)
        size = _size(json_path, entry, top, i)
        if size is None:
            if first_size is None:
                first_size = _image_size(json_path, image_path, i)
            size = first_size
        w, h = size
        K = _intrinsics(json_path, entry, top, w, h, i)
        camera = Camera(opengl_c2w_to_viewmat(c2w), K, w, h)
        if downscale != 1:
            camera = camera.scaled(1.0 / downscale)
        frames.append(Frame(image_path, time, camera, entry.get("camera_id"), downscale=downscale))
    return SceneSplit(
        root=root,
        split=split,
        frames=frames,
        **_scene_facts(json_path, top),
        meta={k: v for k, v in top.items() if k != "frames"},
    )
