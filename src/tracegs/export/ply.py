"""Gaussians written as PLY in the 3DGS layout (plyfile); reading initial points is ``data/points.py``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from ..utils import _atomic


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
