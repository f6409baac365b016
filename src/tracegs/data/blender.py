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
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .cameras import Camera, opengl_c2w_to_viewmat
from .frames import Frame, SceneSplit, fail, read_json

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".exr")


def _resolve_image(json_path: Path, file_path: str) -> Path:
    """The image a ``file_path`` names; without a suffix (D-NeRF writes ``./train/r_000``) the first
    of ``.png``, ``.jpg``, ``.jpeg`` that exists (``.png`` if none does, for the error message)."""
    p = (json_path.parent / file_path).resolve()
    if p.suffix.lower() in IMAGE_SUFFIXES:
        return p
    candidates = [p.with_name(p.name + suffix) for suffix in IMAGE_SUFFIXES[:3]]
    return next((c for c in candidates if c.is_file()), candidates[0])


def _image_size(path: Path) -> tuple[int, int]:
    props = iio.improps(path)
    return int(props.shape[1]), int(props.shape[0])


def _intrinsics(json_path: Path, entry: dict, top: dict, width: int, height: int, index: int) -> torch.Tensor:
    """Intrinsics from per-frame keys first, then the file's top-level keys."""

    def get(key):
        return entry.get(key, top.get(key))

    fx, fy = get("fl_x"), get("fl_y")
    if fx is None and get("camera_angle_x") is not None:
        fx = 0.5 * width / math.tan(0.5 * float(get("camera_angle_x")))
    if fy is None and get("camera_angle_y") is not None:
        fy = 0.5 * height / math.tan(0.5 * float(get("camera_angle_y")))
    if fx is None:
        raise fail(json_path, f"frame {index}: no intrinsics (camera_angle_x or fl_x)")
    fy = fx if fy is None else fy
    cx = float(get("cx")) if get("cx") is not None else width / 2
    cy = float(get("cy")) if get("cy") is not None else height / 2
    return torch.tensor([[float(fx), 0, cx], [0, float(fy), cy], [0, 0, 1]], dtype=torch.float32)


def load_blender(root: str | Path, split: str = "train", downscale: int = 1) -> SceneSplit:
    """Parse ``root/transforms_{split}.json`` into frames with cameras (images are not read here).

    ``downscale`` divides the image size (and the intrinsics) by an integer factor; images are
    box-filtered to that size when loaded by :func:`load_image`.
    """
    root = Path(root)
    json_path = root / f"transforms_{split}.json"
    top = read_json(json_path)
    frames = []
    first_size: tuple[int, int] | None = None  # images of one file share a size unless w/h say otherwise
    for i, entry in enumerate(top["frames"]):
        if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
            raise fail(json_path, f"frame {i}: needs 'file_path' and 'transform_matrix'")
        image_path = _resolve_image(json_path, str(entry["file_path"]))
        c2w = torch.as_tensor(np.asarray(entry["transform_matrix"], dtype=np.float64))
        if c2w.shape != (4, 4) or not torch.isfinite(c2w).all():
            raise fail(json_path, f"frame {i}: 'transform_matrix' must be a finite 4x4 matrix")
        w, h = entry.get("w", top.get("w")), entry.get("h", top.get("h"))
        if w is None or h is None:
            if first_size is None:
                if not image_path.is_file():
                    raise fail(json_path, f"frame {i}: image {image_path} not found")
                first_size = _image_size(image_path)
            w, h = first_size
        time = float(entry.get("time", 0.0))
        if not math.isfinite(time):
            raise fail(json_path, f"frame {i}: 'time' must be a finite number")
        if split == "train" and not -1e-6 <= time <= 1 + 1e-6:
            # the fields' time encodings assume the format's [0, 1]: at integer frame indices every
            # sin(2^k pi t) is 0 and all times look alike
            raise fail(
                json_path,
                f"frame {i}: 'time' {time:g} is outside [0, 1]; the Blender / D-NeRF format gives "
                "times normalised to [0, 1] (e.g. frame index / last frame index)",
            )
        K = _intrinsics(json_path, entry, top, int(w), int(h), i)
        camera = Camera(opengl_c2w_to_viewmat(c2w), K, int(w), int(h))
        if downscale != 1:
            camera = camera.scaled(1.0 / downscale)
        frames.append(Frame(image_path, time, camera, entry.get("camera_id")))
    aabb = top.get("aabb")
    return SceneSplit(
        root=root,
        split=split,
        frames=frames,
        background=tuple(float(c) for c in top.get("background", (1.0, 1.0, 1.0))),
        fps=float(top["fps"]) if "fps" in top else None,
        t_train_end=float(top["t_train_end"]) if "t_train_end" in top else None,
        aabb=torch.tensor(aabb, dtype=torch.float32) if aabb is not None else None,
        meta={k: v for k, v in top.items() if k != "frames"},
    )
