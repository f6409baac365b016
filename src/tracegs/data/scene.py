"""One entry point for every dataset format: ``load_scene`` finds the format of a scene folder and
calls its parser (``blender.py``: Blender / D-NeRF / NVFi json; ``panoptic.py``: the Dynamic 3D
Gaussians layout of CMU Panoptic captures). Frames, splits, errors and image reading: ``frames.py``.
"""

from __future__ import annotations

from pathlib import Path

from .blender import load_blender
from .frames import SPLITS, DatasetError, Frame, SceneSplit, load_image, load_json, load_rgba
from .panoptic import load_panoptic

__all__ = [
    "DatasetError",
    "Frame",
    "SceneSplit",
    "available_splits",
    "load_image",
    "load_json",
    "load_rgba",
    "load_scene",
]


def load_scene(root: str | Path, split: str = "train", downscale: int = 1) -> SceneSplit:
    """The frames of one split of the scene folder ``root``, with cameras (images are not read here).

    ``root/transforms_{split}.json`` is read as the Blender format; without it, ``root/{split}_meta.json``
    as a Dynamic 3D Gaussians capture. ``downscale`` divides the image size (and the intrinsics) by an
    integer factor; images are box-filtered to that size when loaded by :func:`load_image`.
    """
    root = Path(root)
    if not (root / f"transforms_{split}.json").is_file() and (root / f"{split}_meta.json").is_file():
        return load_panoptic(root, split, downscale)
    return load_blender(root, split, downscale)


def available_splits(root: str | Path) -> list[str]:
    """The splits of ``root`` that have a file in either format, in train / val / test order."""
    root = Path(root)
    return [
        s for s in SPLITS if (root / f"transforms_{s}.json").is_file() or (root / f"{s}_meta.json").is_file()
    ]
