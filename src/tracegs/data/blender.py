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

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .cameras import Camera, opengl_c2w_to_viewmat

SPLITS = ("train", "val", "test")


class DatasetError(ValueError):
    """A dataset file is missing or malformed; the message names the file and the problem."""


@dataclass
class Frame:
    """One image of a split: where it is, when it was taken and by which camera."""

    image_path: Path
    time: float
    camera: Camera
    camera_id: int | None = None
    label: str | None = None
    """A name unique within the split, for files written per frame; default: the image's stem."""

    @property
    def name(self) -> str:
        return self.label or self.image_path.stem

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height


@dataclass
class SceneSplit:
    """The frames of one split plus the scene-level facts the trainer needs."""

    root: Path
    split: str
    frames: list[Frame]
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    fps: float | None = None
    t_train_end: float | None = None
    aabb: torch.Tensor | None = None  # [2, 3] min / max corner of the moving object, if known
    meta: dict = field(default_factory=dict)


def _fail(path: Path, problem: str) -> DatasetError:
    return DatasetError(f"{path}: {problem}")


def load_json(path: Path):
    """A JSON file's contents; a missing or unparsable file is a ``DatasetError`` naming it."""
    if not path.is_file():
        raise _fail(path, "file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise _fail(path, f"not valid JSON ({e})") from None


def read_json(path: Path) -> dict:
    data = load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise _fail(path, "expected an object with a non-empty list 'frames'")
    return data


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
        raise _fail(json_path, f"frame {index}: no intrinsics (camera_angle_x or fl_x)")
    fy = fx if fy is None else fy
    cx = float(get("cx")) if get("cx") is not None else width / 2
    cy = float(get("cy")) if get("cy") is not None else height / 2
    return torch.tensor([[float(fx), 0, cx], [0, float(fy), cy], [0, 0, 1]], dtype=torch.float32)


def load_scene(root: str | Path, split: str = "train", downscale: int = 1) -> SceneSplit:
    """Parse ``root/transforms_{split}.json`` into frames with cameras (images are not read here).

    ``downscale`` divides the image size (and the intrinsics) by an integer factor; images are
    box-filtered to that size when loaded by :func:`load_image`.
    """
    root = Path(root)
    json_path = root / f"transforms_{split}.json"
    if not json_path.is_file() and (root / f"{split}_meta.json").is_file():
        from .panoptic import load_panoptic  # a capture in the Dynamic 3D Gaussians layout

        return load_panoptic(root, split, downscale)
    top = read_json(json_path)
    frames = []
    first_size: tuple[int, int] | None = None  # images of one file share a size unless w/h say otherwise
    for i, entry in enumerate(top["frames"]):
        if not isinstance(entry, dict) or "file_path" not in entry or "transform_matrix" not in entry:
            raise _fail(json_path, f"frame {i}: needs 'file_path' and 'transform_matrix'")
        image_path = _resolve_image(json_path, str(entry["file_path"]))
        c2w = torch.as_tensor(np.asarray(entry["transform_matrix"], dtype=np.float64))
        if c2w.shape != (4, 4) or not torch.isfinite(c2w).all():
            raise _fail(json_path, f"frame {i}: 'transform_matrix' must be a finite 4x4 matrix")
        w, h = entry.get("w", top.get("w")), entry.get("h", top.get("h"))
        if w is None or h is None:
            if first_size is None:
                if not image_path.is_file():
                    raise _fail(json_path, f"frame {i}: image {image_path} not found")
                first_size = _image_size(image_path)
            w, h = first_size
        time = float(entry.get("time", 0.0))
        if not math.isfinite(time):
            raise _fail(json_path, f"frame {i}: 'time' must be a finite number")
        if split == "train" and not -1e-6 <= time <= 1 + 1e-6:
            # the fields' time encodings assume the format's [0, 1]: at integer frame indices every
            # sin(2^k pi t) is 0 and all times look alike
            raise _fail(
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


def load_rgba(frame: Frame) -> torch.Tensor:
    """Read a frame's image as float [H, W, 4] in [0, 1] (alpha = 1 for images without one)."""
    path = frame.image_path
    if not path.is_file():
        raise DatasetError(f"{path}: image not found")
    try:
        arr = iio.imread(path)
    except Exception as e:  # imageio raises many types for corrupt files
        raise DatasetError(f"{path}: cannot read image ({e})") from None
    img = torch.from_numpy(np.ascontiguousarray(arr)).float()
    img = img / (65535.0 if arr.dtype == np.uint16 else 255.0 if arr.dtype == np.uint8 else 1.0)
    if img.ndim == 2:
        img = img[..., None].expand(-1, -1, 3)
    if img.shape[-1] == 3:
        img = torch.cat([img, torch.ones_like(img[..., :1])], dim=-1)
    H, W = frame.height, frame.width
    if img.shape[:2] != (H, W):
        fy, fx = img.shape[0] / H, img.shape[1] / W
        if fx != fy or fx != int(fx):
            raise DatasetError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, expected {W}x{H}")
        # box-filter premultiplied colour so that edges do not pick up the hidden colour of empty pixels
        premult = torch.cat([img[..., :3] * img[..., 3:], img[..., 3:]], dim=-1)
        small = torch.nn.functional.interpolate(premult.permute(2, 0, 1)[None], size=(H, W), mode="area")
        small = small[0].permute(1, 2, 0)
        img = torch.cat([small[..., :3] / small[..., 3:].clamp_min(1e-8), small[..., 3:]], dim=-1)
    return img[..., :4].contiguous()


def load_image(frame: Frame, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """Read a frame's image as float [H, W, 3] in [0, 1], RGBA composited on ``background``."""
    rgba = load_rgba(frame)
    alpha = rgba[..., 3:]
    return (rgba[..., :3] * alpha + torch.tensor(background, dtype=rgba.dtype) * (1 - alpha)).contiguous()


def available_splits(root: str | Path) -> list[str]:
    root = Path(root)
    return [
        s for s in SPLITS if (root / f"transforms_{s}.json").is_file() or (root / f"{s}_meta.json").is_file()
    ]
