"""Random Gaussians in front of a pinhole camera: the scenes of the rasteriser's tests and benchmark.

N Gaussians uniformly inside a 64-degree pinhole frustum at depths 2..6 (a little beyond the image
edges too), log-normal world scales around 0.03 (a 1-3 px sigma at 128-256 px), random rotations,
opacities in [0.1, 0.9], RGB colours; about 15-60 Gaussians overlap a pixel before early termination,
like a trained 3DGS scene.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .sh import num_sh_bases


def _rotation(axis_angle: Tensor) -> Tensor:
    """Rodrigues: [3] axis-angle -> [3, 3]."""
    theta = axis_angle.norm()
    k = axis_angle / theta
    kx = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=axis_angle.dtype)
    return torch.eye(3, dtype=axis_angle.dtype) + torch.sin(theta) * kx + (1 - torch.cos(theta)) * (kx @ kx)


def random_scene(
    n: int,
    width: int,
    height: int,
    *,
    seed: int = 0,
    sh_degree: int | None = None,
    scale: float = 0.03,
    frac_behind: float = 0.0,
    opacity_range: tuple[float, float] = (0.1, 0.9),
    dtype: torch.dtype = torch.float32,
) -> dict:
    """Random Gaussians in front of a rotated, translated pinhole camera.

    Returns the keyword arguments of :func:`tracegs.render.rasterize` (means, quats, scales,
    opacities, colors, viewmat, K, width, height, sh_degree). ``frac_behind`` of the Gaussians are
    placed behind the camera.
    """
    g = torch.Generator().manual_seed(seed)

    def rand(*shape):
        return torch.rand(*shape, generator=g, dtype=torch.float64)

    fx = fy = 0.8 * width
    K = torch.tensor([[fx, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]], dtype=torch.float64)
    z = 2.0 + 4.0 * rand(n)
    x = (2 * rand(n) - 1) * 1.2 * z * (width / 2) / fx
    y = (2 * rand(n) - 1) * 1.2 * z * (height / 2) / fy
    behind = rand(n) < frac_behind
    z = torch.where(behind, -(0.2 + 3.0 * rand(n)), z)
    p_cam = torch.stack([x, y, z], dim=-1)

    R = _rotation(torch.tensor([0.3, -0.5, 0.2], dtype=torch.float64))
    t = torch.tensor([0.1, -0.2, 0.5], dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3], viewmat[:3, 3] = R, t
    means = (p_cam - t) @ R  # world = R^T (p_cam - t)

    quats = torch.randn(n, 4, generator=g, dtype=torch.float64)
    scales = scale * torch.exp(0.5 * torch.randn(n, 3, generator=g, dtype=torch.float64))
    lo, hi = opacity_range
    opacities = lo + (hi - lo) * rand(n)
    if sh_degree is None:
        colors = rand(n, 3)
    else:
        colors = 0.3 * torch.randn(n, num_sh_bases(sh_degree), 3, generator=g, dtype=torch.float64)
        colors[:, 0] += 0.5 * rand(n, 3)
    out = dict(
        means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, viewmat=viewmat, K=K
    )
    out = {k: v.to(dtype) for k, v in out.items()}
    out.update(width=width, height=height, sh_degree=sh_degree)
    return out
