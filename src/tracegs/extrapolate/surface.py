"""Gaussians that paint onto still surfaces, and the rule that keeps them there after the handover
(``extrapolation.hold_surface``; docs/PHYSICS.md)."""

from __future__ import annotations

import torch

from ..models.gaussians import nearest_neighbours


class SurfacePainters:
    """Moving Gaussians amid still ones (``extrapolation.hold_surface``): ``rows`` [M] into the Gaussians,
    the still Gaussians' positions ``surface`` [S, 3], and each painter's reach [M]: twice its distance
    from the surface at the handover, or twice the surface's median spacing where that is larger. The
    physics stops a painter for good at the first step that would take it out of reach."""

    def __init__(self, means: torch.Tensor, rows: torch.Tensor, surface: torch.Tensor, spacing: torch.Tensor):
        self.rows, self.surface = rows, surface
        self.reach = 2.0 * torch.maximum(self._distance(means[rows]), spacing)

    @classmethod
    def find(
        cls, means: torch.Tensor, moving: torch.Tensor, fraction: float, neighbours: int
    ) -> SurfacePainters | None:
        """The moving Gaussians at least ``fraction`` of whose ``neighbours`` nearest Gaussians (at
        ``means`` [N, 3]) do not move (``moving`` [N] bool), and the still ones as their surface; None
        where there are none."""
        rows, still = moving.nonzero().squeeze(1), (~moving).nonzero().squeeze(1)
        k = min(neighbours, means.shape[0] - 1)
        if k < 1 or rows.numel() == 0 or still.numel() < 2:
            return None
        near = nearest_neighbours(means, k, of=rows)[1]
        rows = rows[(~moving)[near].float().mean(-1) >= fraction]
        if rows.numel() == 0:
            return None
        surface = means[still]
        spacing = nearest_neighbours(surface, 1)[0].sqrt().median()
        return cls(means, rows, surface, spacing)

    def _distance(self, points: torch.Tensor) -> torch.Tensor:
        """[M] distance of each point to the nearest still Gaussian (in chunks of at most 2^24 pairs)."""
        rows = max(1, (1 << 24) // self.surface.shape[0])
        return torch.cat([torch.cdist(p, self.surface).amin(dim=1) for p in points.split(rows)])

    def off(self, points: torch.Tensor) -> torch.Tensor:
        """[M] bool: the painters that ``points`` [M, 3] (their positions) puts out of reach."""
        return self._distance(points) > self.reach
