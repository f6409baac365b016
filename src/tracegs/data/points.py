"""Initial points of a scene (``points3d.ply``, e.g. from SfM), read with plyfile."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData


def read_points(path: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """Positions [N, 3] and colours [N, 3] in [0, 1] (grey if the file has none) of a PLY vertex list."""
    try:
        vertex = PlyData.read(str(path))["vertex"]
    except Exception as e:  # plyfile raises several types for malformed files
        raise ValueError(f"{path}: cannot read a PLY vertex list ({e})") from None
    names = vertex.data.dtype.names
    if not {"x", "y", "z"} <= set(names):
        raise ValueError(f"{path}: PLY vertices need x, y, z")
    xyz = np.stack([vertex["x"], vertex["y"], vertex["z"]], axis=1).astype(np.float32)
    if {"red", "green", "blue"} <= set(names):
        rgb = np.stack([vertex["red"], vertex["green"], vertex["blue"]], axis=1).astype(np.float32) / 255.0
    else:
        rgb = np.full_like(xyz, 0.5)
    return torch.from_numpy(xyz), torch.from_numpy(rgb)
