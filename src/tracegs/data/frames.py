"""What every dataset parser returns: frames with cameras, a split with the scene-level facts, the
errors that name a bad file, and the reading of images (composited on the scene's background).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from .cameras import Camera

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


def fail(path: Path, problem: str) -> DatasetError:
    return DatasetError(f"{path}: {problem}")


def load_json(path: Path):
    """A JSON file's contents; a missing or unparsable file is a ``DatasetError`` naming it."""
    if not path.is_file():
        raise fail(path, "file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise fail(path, f"not valid JSON ({e})") from None


def read_json(path: Path) -> dict:
    data = load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise fail(path, "expected an object with a non-empty list 'frames'")
    return data


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
