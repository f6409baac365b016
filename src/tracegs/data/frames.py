"""What every dataset parser returns: frames with cameras, a split with the scene-level facts, the
errors that name a bad file, and the reading of images (composited on the scene's background).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import torch

from ..image_metrics import as_rgba, read_image_array
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
    downscale: int = 1
    """The factor by which the image file is larger than ``camera`` (``--downscale``)."""

    @property
    def name(self) -> str:
        return self.label or self.image_path.stem

    @property
    def width(self) -> int:
        return self.camera.width

    @property
    def height(self) -> int:
        return self.camera.height


def camera_key(f: Frame) -> tuple:
    """A camera's identity: its id when the dataset gives one, else its pose (to 1e-4)."""
    if f.camera_id is not None:
        return ("id", f.camera_id)
    return tuple(round(float(v), 4) for v in f.camera.viewmat[:3].flatten())


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
    if path.is_dir():
        raise fail(path, "is a folder, expected a JSON file")
    if not path.is_file():
        raise fail(path, "file not found")
    try:
        return json.loads(path.read_text())
    except UnicodeDecodeError:
        raise fail(path, "not valid JSON (not UTF-8 text)") from None
    except json.JSONDecodeError as e:
        raise fail(path, f"not valid JSON ({e})") from None


def read_json(path: Path) -> dict:
    """A split file: a JSON object with a non-empty list ``frames`` (``DatasetError`` naming it else)."""
    data = load_json(path)
    if not isinstance(data, dict):
        raise fail(path, f"expected an object with a non-empty list 'frames', got a {type(data).__name__}")
    if "frames" not in data:
        raise fail(path, "no 'frames' (expected an object with a non-empty list 'frames')")
    if not isinstance(data["frames"], list):
        raise fail(path, f"'frames' must be a list, got a {type(data['frames']).__name__}")
    if not data["frames"]:
        raise fail(path, "'frames' is empty: the split has no frames (remove the file if it has none)")
    return data


def load_rgba(frame: Frame) -> torch.Tensor:
    """Read a frame's image as float [H, W, 4] in [0, 1] (alpha = 1 for images without one); grey,
    grey + alpha, RGB and RGBA files of 8 or 16 bits; box-filtered by ``frame.downscale``."""
    path = frame.image_path
    try:
        rgba = as_rgba(read_image_array(path), path)
    except (FileNotFoundError, ValueError) as e:
        raise DatasetError(str(e)) from None
    img = torch.from_numpy(rgba)
    H, W, ds = frame.height, frame.width, frame.downscale
    if img.shape[:2] == (H * ds, W * ds) and ds > 1:
        # box-filter premultiplied colour so that edges do not pick up the hidden colour of empty pixels
        premult = torch.cat([img[..., :3] * img[..., 3:], img[..., 3:]], dim=-1)
        small = torch.nn.functional.interpolate(premult.permute(2, 0, 1)[None], size=(H, W), mode="area")
        small = small[0].permute(1, 2, 0)
        img = torch.cat([small[..., :3] / small[..., 3:].clamp_min(1e-8), small[..., 3:]], dim=-1)
    elif img.shape[:2] != (H, W):
        size = f"{img.shape[1]}x{img.shape[0]}"
        if ds > 1 and (img.shape[0] % ds or img.shape[1] % ds):
            raise DatasetError(f"{path}: --downscale {ds} does not divide the image size {size}")
        raise DatasetError(f"{path}: image is {size}, expected {W * ds}x{H * ds} (the split's image size)")
    return img.contiguous()


def load_image(frame: Frame, background=(1.0, 1.0, 1.0)) -> torch.Tensor:
    """Read a frame's image as float [H, W, 3] in [0, 1], RGBA composited on ``background``."""
    rgba = load_rgba(frame)
    alpha = rgba[..., 3:]
    return (rgba[..., :3] * alpha + torch.tensor(background, dtype=rgba.dtype) * (1 - alpha)).contiguous()
