"""Adaptive density control of 3DGS as a Strategy object (the gsplat pattern).

One signature for every strategy: ``initialize_state()``, ``step_pre_backward(...)`` (ask the renderer
to keep the view-space gradient), ``step_post_backward(...)`` (accumulate it; clone, split, prune,
reset opacities on schedule). Each Gaussian parameter has its own Adam optimiser so that rows can be
added and removed together with their optimiser moments.
N: Gaussians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from ..config import DensifyConfig
from ..data.cameras import scene_extent_from_cameras
from ..physics.so3 import quat_to_rotmat

__all__ = [
    "DefaultStrategy",
    "DensifyConfig",
    "duplicate",
    "remove",
    "scene_extent_from_cameras",
    "split_gaussians",
]


@dataclass
class DefaultStrategy:
    """Clone small, split large Gaussians with high view-space gradient; prune transparent/huge ones."""

    cfg: DensifyConfig
    scene_extent: float
    total_steps: int | None = None
    """Iterations of the whole run; bounds ``refine_stop`` by ``refine_stop_fraction`` of it."""

    @property
    def refine_stop(self) -> int:
        if self.total_steps is None:
            return self.cfg.refine_stop
        return min(self.cfg.refine_stop, int(self.cfg.refine_stop_fraction * self.total_steps))

    def initialize_state(self) -> dict[str, Any]:
        return {"grad2d": None, "count": None}

    def step_pre_backward(self, render_info: dict) -> None:
        means2d = render_info["means2d"]
        if means2d.requires_grad:
            means2d.retain_grad()

    @torch.no_grad()
    def step_post_backward(
        self,
        params: nn.ParameterDict,
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        render_infos: list[dict],
    ) -> dict[str, int]:
        """Accumulate gradients of this step (of each view it rendered); refine on schedule. Returns
        counts of what changed."""
        if step >= self.refine_stop:
            return {}
        report, _ = self._post_backward(
            params, optimizers, state, step, render_infos, None, self.cfg.refine_start
        )
        return report

    def _post_backward(self, params, optimizers, state, step, render_infos, held, refine_after: int):
        """Accumulate this step's gradients; clone, split and prune after step ``refine_after`` on the
        schedule, reset opacities on theirs; of the Gaussians not ``held`` (None: all). ``(report, held)``."""
        cfg = self.cfg
        for info in render_infos:
            self._accumulate(params, state, info)
        report: dict[str, int] = {}
        if step > refine_after and step % cfg.refine_every == 0:
            report, held = self._refine(params, optimizers, state, step, held)
        if cfg.reset_every and step > 0 and step % cfg.reset_every == 0:
            self._reset_opacities(params, optimizers, held)
        return report, held

    def _reset_opacities(self, params, optimizers, held: torch.Tensor | None = None) -> None:
        """3DGS's opacity reset (to ``reset_opacity``), of the Gaussians not ``held`` (None: all)."""
        limit = torch.logit(torch.tensor(self.cfg.reset_opacity * 2)).item()
        opacities = params["opacities"].data
        rows = slice(None) if held is None else ~held
        opacities[rows] = opacities[rows].clamp(max=limit)
        reset_optimizer_state(optimizers["opacities"])

    def _accumulate(self, params, state, info) -> None:
        grad = info["means2d"].grad
        if grad is None:
            return
        n = params["means"].shape[0]
        if state["grad2d"] is None or state["grad2d"].shape[0] != n:
            state["grad2d"] = torch.zeros(n, device=grad.device)
            state["count"] = torch.zeros(n, device=grad.device)
        # Pixel-space gradient -> NDC units, the space 3DGS's threshold is defined in.
        g = grad.detach().clone()
        g[:, 0] *= info["width"] / 2.0
        g[:, 1] *= info["height"] / 2.0
        visible = info["radii"] > 0
        state["grad2d"][visible] += g[visible].norm(dim=-1)
        state["count"][visible] += 1

    @torch.no_grad()
    def refine_moving(
        self,
        params: nn.ParameterDict,
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        render_infos: list[dict],
        held: torch.Tensor | None,
    ) -> tuple[dict[str, int], torch.Tensor | None]:
        """Stage 2's densification of the Gaussians that move (``densify.moving_refine_stop``): as
        ``step_post_backward``, but the Gaussians ``held`` [N] bool (static, None: none) are neither
        grown, pruned nor reset, and growth stops at ``densify.moving_max_gaussians`` moving ones. The
        report, and ``held`` for the new rows (a grown Gaussian moves)."""
        if step >= self.cfg.moving_refine_stop:
            return {}, held
        return self._post_backward(params, optimizers, state, step, render_infos, held, refine_after=-1)

    def _refine(
        self, params, optimizers, state, step, held=None
    ) -> tuple[dict[str, int], torch.Tensor | None]:
        """Clone, split and prune on the accumulated gradients; with ``held`` (stage 2's moving
        densification) only the Gaussians not held, within ``densify.moving_max_gaussians``."""
        cfg = self.cfg
        if state["grad2d"] is None:
            return {}, held
        avg = state["grad2d"] / state["count"].clamp_min(1)
        high = avg > cfg.grow_grad2d
        max_scale = torch.exp(params["scales"]).max(dim=-1).values
        small = max_scale <= cfg.grow_scale3d * self.scene_extent
        n = params["means"].shape[0]
        if held is None:
            budget = max(cfg.max_gaussians - n, 0)
        else:
            high &= ~held
            budget = max(cfg.moving_max_gaussians - int((~held).sum()), 0)
        grow = _strongest(high, avg, budget)  # clone and split each add one Gaussian
        clone, split = grow & small, grow & ~small
        n_clone, n_split = int(clone.sum()), int(split.sum())
        if n_clone:
            duplicate(params, optimizers, clone)
            held = None if held is None else torch.cat([held, torch.zeros_like(held[clone])])
        if n_split:
            split = torch.cat([split, torch.zeros(n_clone, dtype=torch.bool, device=split.device)])
            split_gaussians(params, optimizers, split)
            if held is not None:  # (each split Gaussian's two halves go to the end)
                held = torch.cat(
                    [held[~split], torch.zeros(2 * n_split, dtype=torch.bool, device=held.device)]
                )
        opacity = torch.sigmoid(params["opacities"])
        prune = opacity < cfg.prune_opacity
        if step > cfg.reset_every:
            prune |= torch.exp(params["scales"]).max(dim=-1).values > cfg.prune_scale3d * self.scene_extent
        if held is not None:
            prune &= ~held
        n_prune = int(prune.sum())
        if n_prune == len(prune):
            raise ValueError(
                f"densification at step {step} would prune every Gaussian (opacity below "
                f"--densify.prune-opacity {cfg.prune_opacity:g}, or larger than --densify.prune-scale3d "
                f"{cfg.prune_scale3d:g} of the scene extent): nothing is left to train; check that the "
                "training images show the scene, or lower those settings"
            )
        if n_prune:
            remove(params, optimizers, prune)
            held = None if held is None else held[~prune]
        state["grad2d"] = state["count"] = None
        return {"cloned": n_clone, "split": n_split, "pruned": n_prune}, held


def _strongest(mask: torch.Tensor, score: torch.Tensor, budget: int) -> torch.Tensor:
    """Keep at most ``budget`` of the selected entries: those of highest ``score``. Under a Gaussian
    budget growth then goes where the view-space gradient (the error) is largest, not to whichever
    Gaussians happen to come first."""
    if int(mask.sum()) <= budget:
        return mask
    keep = torch.zeros_like(mask)
    keep[torch.where(mask, score, float("-inf")).topk(budget).indices] = True
    return keep


def _update_rows(params, optimizers, fn_param, fn_moment) -> None:
    """Replace every parameter by ``fn_param(name, p)`` and its Adam moments by ``fn_moment(m)``."""
    for name in list(params.keys()):
        new = nn.Parameter(fn_param(name, params[name].data))
        opt = optimizers[name]
        old = opt.param_groups[0]["params"][0]
        st = opt.state.pop(old, None)
        opt.param_groups[0]["params"][0] = new
        if st is not None:
            opt.state[new] = {
                k: (fn_moment(v) if k in ("exp_avg", "exp_avg_sq") else v) for k, v in st.items()
            }
        params[name] = new


def duplicate(params, optimizers, mask: torch.Tensor) -> None:
    """Clone the selected Gaussians (new copies get zero optimiser moments)."""
    _update_rows(
        params,
        optimizers,
        lambda _, p: torch.cat([p, p[mask]]),
        lambda m: torch.cat([m, torch.zeros_like(m[mask])]),
    )


def remove(params, optimizers, mask: torch.Tensor) -> None:
    keep = ~mask
    _update_rows(params, optimizers, lambda _, p: p[keep], lambda m: m[keep])


def split_gaussians(params, optimizers, mask: torch.Tensor, samples: int = 2) -> None:
    """Replace each selected Gaussian by ``samples`` smaller ones drawn from it (3DGS: scale / 1.6)."""
    sel = mask.nonzero().squeeze(1)
    scales = torch.exp(params["scales"].data[sel])  # [S, 3]
    R = quat_to_rotmat(params["quats"].data[sel])  # [S, 3, 3]
    offsets = torch.randn(samples, len(sel), 3, device=scales.device) * scales
    new_means = (torch.einsum("sij,nsj->nsi", R, offsets) + params["means"].data[sel]).reshape(-1, 3)
    keep = ~mask

    def new_param(name, p):
        if name == "means":
            added = new_means
        elif name == "scales":
            added = torch.log(scales / (0.8 * samples)).repeat(samples, 1)
        else:
            added = p[sel].repeat(samples, *([1] * (p.dim() - 1)))
        return torch.cat([p[keep], added])

    _update_rows(
        params,
        optimizers,
        new_param,
        lambda m: torch.cat(
            [m[keep], torch.zeros((samples * len(sel), *m.shape[1:]), device=m.device, dtype=m.dtype)]
        ),
    )


def reset_optimizer_state(opt: torch.optim.Optimizer) -> None:
    for st in opt.state.values():
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st:
                st[k].zero_()


def log_interp(start: float, end: float, frac: float) -> float:
    """Exponential decay from ``start`` to ``end`` at fraction ``frac`` in [0, 1] (3DGS schedules)."""
    frac = min(max(frac, 0.0), 1.0)
    return math.exp(math.log(start) * (1 - frac) + math.log(end) * frac)
