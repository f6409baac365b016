"""Canonical 3D Gaussians (the scene at t = 0) as a dict of learnable tensors.

N: Gaussians, K: SH coefficients per channel ((degree + 1)^2).
Parameters are stored unconstrained, as 3DGS does: log-scales, opacity logits, raw quaternions (wxyz).
They live in a ``torch.nn.ParameterDict`` so that densification can replace them by name and the
optimiser state can follow (see ``train/strategy.py``).
"""

from __future__ import annotations

import math

import torch
from torch import nn

SH_C0 = 0.28209479177387814  # Y_0^0; colour = SH_C0 * sh0 + 0.5 for degree 0


def num_sh_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def rgb_to_sh0(rgb: torch.Tensor) -> torch.Tensor:
    return (rgb - 0.5) / SH_C0


def create_gaussians(
    means: torch.Tensor,  # [N, 3]
    colors: torch.Tensor,  # [N, 3] in [0, 1]
    sh_degree: int,
    init_opacity: float = 0.1,
    init_scale: torch.Tensor | None = None,  # [N] or None: mean distance to 3 nearest neighbours
) -> nn.ParameterDict:
    """Gaussians at the given points, isotropic, with the 3DGS initial opacity and scale."""
    n = means.shape[0]
    if init_scale is None:
        init_scale = nearest_neighbour_distance(means, k=3)
    log_scales = torch.log(init_scale.clamp_min(1e-7))[:, None].repeat(1, 3)
    quats = torch.zeros(n, 4, device=means.device)
    quats[:, 0] = 1
    sh_rest = torch.zeros(n, num_sh_coeffs(sh_degree) - 1, 3, device=means.device)
    return nn.ParameterDict(
        {
            "means": nn.Parameter(means.clone()),
            "quats": nn.Parameter(quats),
            "scales": nn.Parameter(log_scales),
            "opacities": nn.Parameter(
                torch.full((n,), math.log(init_opacity / (1 - init_opacity)), device=means.device)
            ),
            "sh0": nn.Parameter(rgb_to_sh0(colors)[:, None, :].clone()),
            "shN": nn.Parameter(sh_rest),
        }
    )


def random_gaussians(
    n: int, aabb: torch.Tensor, sh_degree: int, generator: torch.Generator | None = None, **kwargs
) -> nn.ParameterDict:
    """``n`` Gaussians uniformly in the box ``aabb`` [2, 3] with random colours (3DGS random init)."""
    lo, hi = aabb[0], aabb[1]
    means = lo + (hi - lo) * torch.rand(n, 3, generator=generator, device=aabb.device)
    colors = torch.rand(n, 3, generator=generator, device=aabb.device)
    return create_gaussians(means, colors, sh_degree, **kwargs)


def nearest_neighbours(
    points: torch.Tensor, k: int, chunk: int = 4096, of: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Squared distances and indices of the ``k`` nearest other points, [N, k] each (closest first);
    with ``of`` (indices [M] into ``points``), of those points only ([M, k])."""
    queries = points if of is None else points[of]
    d2s, idxs = [], []
    for start in range(0, queries.shape[0], chunk):
        d2 = torch.cdist(queries[start : start + chunk], points).pow(2)
        d2, idx = d2.topk(min(k + 1, points.shape[0]), dim=1, largest=False)
        d2s.append(d2[:, 1:])  # drop the point itself
        idxs.append(idx[:, 1:])
    return torch.cat(d2s), torch.cat(idxs)


def nearest_neighbour_distance(points: torch.Tensor, k: int = 3, chunk: int = 4096) -> torch.Tensor:
    """Root mean squared distance to the ``k`` nearest other points, [N] (3DGS's initial scale)."""
    return nearest_neighbours(points, k, chunk)[0].mean(dim=1).sqrt()


def empty_like_params(state: dict[str, torch.Tensor]) -> nn.ParameterDict:
    """A parameter dict with the shapes of a saved state dict (for loading a checkpoint)."""
    return nn.ParameterDict({k: nn.Parameter(torch.zeros_like(v)) for k, v in state.items()})
