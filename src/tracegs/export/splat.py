"""Gaussians in the ``.splat`` format of antimatter15's web viewer (also read by SuperSplat and other
three.js / WebGL viewers): a headerless list of 32-byte records, little-endian,

    position 3 x float32 | scale 3 x float32 (linear) | colour RGBA 4 x uint8 | rotation 4 x uint8

the colour the view-independent one (``0.5 + SH_C0 * f_dc``; the higher SH bands are dropped), alpha the
opacity (``sigmoid`` of the logit), the rotation the unit wxyz quaternion mapped to ``q * 128 + 128``;
sorted by decreasing ``scale_x * scale_y * scale_z * alpha``, as the format's reference converter
sorts, so that a viewer that streams the file shows the largest splats first.

The format is 32 bytes a Gaussian and is written here with numpy, no library needed. Quantisation
rounds to the nearest step (the reference converter truncates; the decoding is the same).

N: Gaussians.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..models.gaussians import SH_C0
from ..utils import atomic_write_bytes

SPLAT_DTYPE = np.dtype(
    [("position", "<f4", (3,)), ("scale", "<f4", (3,)), ("rgba", "u1", (4,)), ("rotation", "u1", (4,))]
)
"""One record of a ``.splat`` file (32 bytes)."""


def _quantise(x: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(x), 0, 255).astype(np.uint8)


def gaussians_to_splat(params: dict[str, torch.Tensor]) -> np.ndarray:
    """[N] records of ``SPLAT_DTYPE`` (in the file's order) from a parameter dict (``means`` [N, 3],
    ``quats`` [N, 4] wxyz, log-``scales`` [N, 3], ``opacities`` [N] logits, ``sh0`` [N, 1, 3])."""
    p = {k: params[k].detach().double().cpu().numpy() for k in ("means", "quats", "scales", "opacities")}
    n = len(p["means"])
    rgb = 0.5 + SH_C0 * params["sh0"].detach().double().cpu().numpy().reshape(n, 3)
    alpha = 1.0 / (1.0 + np.exp(-p["opacities"]))
    quats = p["quats"] / np.maximum(np.linalg.norm(p["quats"], axis=1, keepdims=True), 1e-12)
    records = np.empty(n, dtype=SPLAT_DTYPE)
    records["position"] = p["means"]
    records["scale"] = np.exp(p["scales"])
    records["rgba"] = _quantise(255 * np.concatenate([rgb, alpha[:, None]], axis=1))
    records["rotation"] = _quantise(quats * 128 + 128)
    order = np.argsort(-np.exp(p["scales"].sum(axis=1)) * alpha, kind="stable")
    return records[order]


def write_splat(params: dict[str, torch.Tensor], path: Path) -> Path:
    """Gaussians (a parameter dict, see :func:`gaussians_to_splat`) as a ``.splat`` file, written
    atomically."""
    return atomic_write_bytes(Path(path), gaussians_to_splat(params).tobytes())


def read_splat(path: Path) -> dict[str, np.ndarray]:
    """The Gaussians of a ``.splat`` file, decoded as a viewer decodes them: ``means`` [N, 3], linear
    ``scales`` [N, 3], ``rgba`` [N, 4] in [0, 1], ``quats`` [N, 4] wxyz (unnormalised, ``(q - 128) /
    128``); ValueError naming the file when its size is not a multiple of 32 bytes."""
    raw = Path(path).read_bytes()
    if len(raw) % SPLAT_DTYPE.itemsize:
        raise ValueError(
            f"{path}: not a .splat file ({len(raw)} bytes, not a multiple of {SPLAT_DTYPE.itemsize})"
        )
    records = np.frombuffer(raw, dtype=SPLAT_DTYPE)
    return {
        "means": records["position"].copy(),
        "scales": records["scale"].copy(),
        "rgba": records["rgba"] / 255.0,
        "quats": (records["rotation"].astype(np.float64) - 128) / 128,
    }
