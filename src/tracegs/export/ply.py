"""Gaussians as PLY in the layout of the original 3DGS code (INRIA), the one splat viewers and editors
open (SuperSplat, antimatter15's viewer, ...); reading a scene's initial points is ``data/points.py``.

One ``vertex`` element, float32, binary little-endian, properties in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..3(K-1)-1 opacity scale_0..2 rot_0..3``. The values are the
parameters as tracegs stores them, which are 3DGS's: opacity a logit, scales logs, rotation a wxyz
quaternion (w is ``rot_0``; not necessarily unit length, viewers normalise it), normals zero. ``f_rest``
is channel-major: the K - 1 higher SH coefficients of red, then those of green, then of blue.

N: Gaussians, K: SH coefficients per channel ((degree + 1)^2).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from plyfile import PlyData, PlyElement

from ..utils import _atomic, first_line

NORMALS = ("nx", "ny", "nz")
"""Written as zeros (viewers expect them); a PLY without them is read all the same."""
FIXED_BEFORE = ("x", "y", "z", *NORMALS, "f_dc_0", "f_dc_1", "f_dc_2")
FIXED_AFTER = ("opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3")


def property_names(num_rest: int) -> list[str]:
    """The vertex properties of a 3DGS PLY with ``num_rest`` = K - 1 higher SH coefficients per channel."""
    return [*FIXED_BEFORE, *(f"f_rest_{i}" for i in range(3 * num_rest)), *FIXED_AFTER]


def gaussians_to_vertices(params: dict[str, torch.Tensor]) -> np.ndarray:
    """[N] structured float32 array of the PLY's vertices from a parameter dict (``means`` [N, 3],
    ``quats`` [N, 4] wxyz, log-``scales`` [N, 3], ``opacities`` [N] logits, ``sh0`` [N, 1, 3], ``shN``
    [N, K-1, 3])."""
    p = {k: params[k].detach().float().cpu().numpy() for k in ("means", "quats", "scales", "opacities")}
    n = len(p["means"])
    sh0 = params["sh0"].detach().float().cpu().numpy().reshape(n, 3)
    shn = params["shN"].detach().float().cpu().numpy()  # [N, K-1, 3]
    rest = shn.transpose(0, 2, 1).reshape(n, -1)  # [N, 3 (K-1)]: channel-major, as INRIA writes it
    columns = np.concatenate(
        [p["means"], np.zeros((n, 3), np.float32), sh0, rest, p["opacities"].reshape(n, 1), p["scales"], p["quats"]],
        axis=1,
    )  # fmt: skip
    names = property_names(shn.shape[1])
    vertices = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        vertices[name] = columns[:, i]
    return vertices


def write_gaussians(params: dict[str, torch.Tensor], path: Path) -> Path:
    """Gaussians (a parameter dict, see :func:`gaussians_to_vertices`) as a 3DGS PLY, written atomically."""
    element = PlyElement.describe(gaussians_to_vertices(params), "vertex")
    return _atomic(Path(path), lambda tmp: PlyData([element], byte_order="<").write(tmp))


def read_gaussians(path: Path, device: torch.device | str = "cpu") -> dict[str, torch.Tensor]:
    """The parameter dict (``means``, ``quats``, ``scales``, ``opacities``, ``sh0``, ``shN``; shapes as
    :func:`gaussians_to_vertices` takes them) of a 3DGS PLY; ValueError naming the file when it is not
    one."""
    try:
        ply = PlyData.read(str(path))
    except Exception as err:  # plyfile raises several types for malformed files
        raise ValueError(f"{path}: cannot read it as a PLY ({first_line(err)})") from None
    if "vertex" not in ply:
        raise ValueError(f"{path}: not a 3DGS PLY (no vertex element)")
    vertex = ply["vertex"]
    names = vertex.data.dtype.names
    num_rest = _num_rest(path, names)
    missing = [name for name in property_names(num_rest) if name not in names and name not in NORMALS]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY: no {', '.join(missing)} among its vertex properties")

    def stack(*cols: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([vertex[c] for c in cols], axis=1).astype(np.float32)).to(device)

    n = len(vertex.data)
    rest = stack(*(f"f_rest_{i}" for i in range(3 * num_rest))) if num_rest else torch.zeros(n, 0)
    return {
        "means": stack("x", "y", "z"),
        "quats": stack("rot_0", "rot_1", "rot_2", "rot_3"),
        "scales": stack("scale_0", "scale_1", "scale_2"),
        "opacities": stack("opacity")[:, 0],
        "sh0": stack("f_dc_0", "f_dc_1", "f_dc_2")[:, None, :],
        "shN": rest.reshape(n, 3, num_rest).transpose(1, 2).contiguous().to(device),
    }


def _num_rest(path: Path, names: tuple[str, ...]) -> int:
    """K - 1 from the ``f_rest_*`` properties (3 (K - 1) of them, numbered from 0)."""
    count = sum(name.startswith("f_rest_") for name in names)
    if count % 3 or any(f"f_rest_{i}" not in names for i in range(count)):
        raise ValueError(f"{path}: not a 3DGS PLY: {count} f_rest_* properties, expected 3 per coefficient")
    return count // 3
