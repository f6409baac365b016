"""Reader for multi-view captures in the Dynamic 3D Gaussians layout (CMU Panoptic Sports).

A scene folder holds ``{split}_meta.json`` and the images under ``ims/``. The json gives, per frame
index and camera: ``k`` intrinsics [T][C][3][3], ``w2c`` world-to-camera [T][C][4][4] (OpenCV axes,
as our cameras), ``fn`` the image path under ``ims/`` and ``cam_id``, with the image size ``w``, ``h``.
Frame index i of T becomes time i / (T - 1), the [0, 1] of the Blender / D-NeRF format, so every
command takes such a folder as ``--data`` (``load_scene`` chooses this reader when the folder has no
``transforms_{split}.json``). Images are opaque photographs; the background colour is black.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from .cameras import Camera
from .frames import DatasetError, Frame, SceneSplit, load_json

KEYS = ("w", "h", "k", "w2c", "fn", "cam_id")


def load_panoptic(root: str | Path, split: str = "train", downscale: int = 1) -> SceneSplit:
    """The frames of ``root/{split}_meta.json`` (see the module docstring)."""
    root = Path(root)
    path = root / f"{split}_meta.json"
    meta = load_json(path)
    missing = [k for k in KEYS if not isinstance(meta, dict) or k not in meta]
    if missing:
        raise DatasetError(
            f"{path}: missing {', '.join(missing)} (the Dynamic 3D Gaussians layout has {KEYS})"
        )
    names, ids = meta["fn"], meta["cam_id"]
    try:
        K = np.asarray(meta["k"], dtype=np.float64)
        w2c = np.asarray(meta["w2c"], dtype=np.float64)
    except ValueError:
        raise DatasetError(f"{path}: 'k' and 'w2c' must be arrays of one camera count per frame") from None
    T = len(names)
    C = len(names[0]) if T else 0
    if T == 0 or C == 0:
        raise DatasetError(f"{path}: no frames")
    if K.shape != (T, C, 3, 3) or w2c.shape != (T, C, 4, 4) or np.shape(ids) != (T, C):
        raise DatasetError(
            f"{path}: expected k [T][C][3][3], w2c [T][C][4][4] and cam_id [T][C] for the {T} x {C} "
            f"file names, got {list(K.shape)}, {list(w2c.shape)} and {list(np.shape(ids))}"
        )
    if not (np.isfinite(K).all() and np.isfinite(w2c).all()):
        raise DatasetError(f"{path}: 'k' and 'w2c' must be finite")
    width, height = meta["w"], meta["h"]
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
        raise DatasetError(
            f"{path}: 'w' and 'h' must be positive whole numbers of pixels, got {width!r}, {height!r}"
        )
    frames = []
    for i in range(T):
        time = i / (T - 1) if T > 1 else 0.0
        for c in range(C):
            camera = Camera(
                torch.tensor(w2c[i, c], dtype=torch.float32),
                torch.tensor(K[i, c], dtype=torch.float32),
                width,
                height,
            )
            if downscale != 1:
                camera = camera.scaled(1.0 / downscale)
            cam_id = int(ids[i][c])
            label = f"c{cam_id:02d}_f{i:03d}"
            image = Path(os.path.abspath(root / "ims" / names[i][c]))  # (links kept: masks sit beside)
            frames.append(Frame(image, time, camera, cam_id, label, downscale))
    return SceneSplit(
        root=root,
        split=split,
        frames=frames,
        background=(0.0, 0.0, 0.0),
        fps=float(max(T - 1, 1)),
        meta={"layout": "panoptic"},
    )
