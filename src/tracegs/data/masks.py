"""Foreground masks of a capture's frames, where the scene folder has them.

* CMU Panoptic layout (``ims/`` images): ``seg/<same path>.png``, the Dynamic 3D Gaussians release's
  foreground masks (non-zero = foreground).
* Any other layout (a Blender-layout split, ``tracegs synth``): ``masks/<image path relative to the
  scene folder>.png``, non-zero = foreground.

A mask may be larger than the frame by the frame's integer ``--downscale`` factor; it is then reduced
by nearest sampling, as the images are resized.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from .frames import DatasetError, Frame


def foreground_path(root: str | Path, frame: Frame) -> Path:
    """Where the foreground mask of ``frame`` (of the scene folder ``root``) is (see the module docstring)."""
    # as written, then with links resolved: a scene folder may link its images from elsewhere
    for root_, image in (
        (Path(os.path.abspath(root)), Path(os.path.abspath(frame.image_path))),
        (Path(root).resolve(), Path(frame.image_path).resolve()),
    ):
        for base, folder in ((root_ / "ims", root_ / "seg"), (root_, root_ / "masks")):
            try:
                return (folder / image.relative_to(base)).with_suffix(".png")
            except ValueError:
                continue
    image = Path(frame.image_path)
    raise DatasetError(f"{image}: the image lies outside {root}, so its mask cannot be found")


def read_id_mask(path: Path, height: int, width: int) -> np.ndarray:
    """[height, width] int64 ids of the one-channel PNG ``path`` (a mask of an integer multiple of that
    size reduced by nearest sampling); DatasetError naming the file when it cannot be read or sized."""
    import imageio.v2 as imageio

    try:
        raw = np.asarray(imageio.imread(path))
    except Exception as e:  # imageio raises many kinds for a broken file
        raise DatasetError(f"{path}: cannot read the mask ({e})") from None
    if raw.ndim == 3:
        raw = raw[..., 0]
    if raw.ndim != 2:
        raise DatasetError(f"{path}: a mask must be one channel of ids, got shape {raw.shape}")
    ids = raw.astype(np.int64)
    if ids.shape != (height, width):
        fy, fx = ids.shape[0] / height, ids.shape[1] / width
        if fy != fx or fy != int(fy) or fy < 1:
            raise DatasetError(
                f"{path}: mask of {ids.shape[1]}x{ids.shape[0]} for an image of {width}x{height}"
            )
        f = int(fy)
        ids = ids[f // 2 :: f, f // 2 :: f]
    return ids


def read_foreground(root: str | Path, frame: Frame) -> np.ndarray | None:
    """[H, W] bool foreground of ``frame`` at its camera's size, or None when it has no mask file."""
    path = foreground_path(root, frame)
    if not path.is_file():
        return None
    return read_id_mask(path, frame.height, frame.width) > 0
