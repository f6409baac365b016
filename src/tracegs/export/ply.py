"""Point clouds in PLY (plyfile): reading initial points, writing Gaussians in the 3DGS layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from ..utils import _atomic


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


def write_gaussians(params: dict[str, torch.Tensor], path: Path) -> Path:
    """Canonical Gaussians as a 3DGS-style PLY (x, y, z, f_dc_*, f_rest_*, opacity, scale_*, rot_*)."""
    means = params["means"].detach().cpu().numpy()
    sh0 = params["sh0"].detach().cpu().numpy().reshape(len(means), -1)
    shn = params["shN"].detach().cpu().transpose(1, 2).reshape(len(means), -1).numpy()
    cols = {
        **{a: means[:, i] for i, a in enumerate("xyz")},
        **{f"f_dc_{i}": sh0[:, i] for i in range(sh0.shape[1])},
        **{f"f_rest_{i}": shn[:, i] for i in range(shn.shape[1])},
        "opacity": params["opacities"].detach().cpu().numpy(),
        **{f"scale_{i}": params["scales"].detach().cpu().numpy()[:, i] for i in range(3)},
        **{f"rot_{i}": params["quats"].detach().cpu().numpy()[:, i] for i in range(4)},
    }
    data = np.empty(len(means), dtype=[(k, "f4") for k in cols])
    for k, v in cols.items():
        data[k] = v
    return _atomic(Path(path), lambda tmp: PlyData([PlyElement.describe(data, "vertex")]).write(tmp))
