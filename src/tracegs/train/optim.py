"""Optimisers and learning-rate schedules (3DGS for the Gaussians, one Adam for both fields)."""

from __future__ import annotations

import torch
from torch import nn

from .strategy import log_interp


def gaussian_lrs(cfg, extent: float) -> dict[str, float]:
    """The starting learning rate of every Gaussian parameter (``means`` then decays: ``means_lr``)."""
    return {
        "means": cfg.means_lr * extent,
        "quats": cfg.quat_lr,
        "scales": cfg.scale_lr,
        "opacities": cfg.opacity_lr,
        "sh0": cfg.sh0_lr,
        "shN": cfg.shN_lr,
    }


def gaussian_optimizers(params: nn.ParameterDict, cfg, extent: float) -> dict[str, torch.optim.Optimizer]:
    """One Adam per Gaussian parameter (densification replaces rows of each independently), fused
    where it can be (six updates 0.50 -> 0.26 ms a step at 7k Gaussians, 2 CPU threads)."""
    lrs = gaussian_lrs(cfg, extent)
    return {
        name: torch.optim.Adam([params[name]], lr=lrs[name], eps=1e-15, fused=_fusable([params[name]]))
        for name in params.keys()
    }


def _fusable(params: list[torch.Tensor]) -> bool | None:
    """True where torch's fused Adam runs (float32 on the CPU or CUDA): the same update in one pass
    per tensor; None (the default loop) elsewhere."""
    return all(p.device.type in ("cpu", "cuda") and p.dtype == torch.float32 for p in params) or None


def field_optimizer(groups: dict[str, list[nn.Parameter]], cfg) -> torch.optim.Optimizer | None:
    """One Adam for both fields. ``groups`` names the parameter groups (``"fields"``: the MLPs;
    ``"grid"``: HexPlane planes, which 4DGS trains with a ten times larger rate); empty ones are left out."""
    param_groups = [{"params": p, "lr": cfg.field_lr, "name": name} for name, p in groups.items() if p]
    if not param_groups:
        return None
    # the fused kernel is the same update in one pass per tensor: half the time of the default loop
    # on the CPU (6 against 12 ms per step for the 2.4M HexPlane values)
    params = [p for group in param_groups for p in group["params"]]
    return torch.optim.Adam(param_groups, eps=1e-15, fused=_fusable(params))


def step_adams(optimizers: list[torch.optim.Optimizer | None]) -> None:
    """``opt.step()`` for each of ``optimizers`` (None skipped): fused Adams with their state made
    call torch's fused kernel themselves (one ``_foreach_add_`` for every step count, then one
    ``_fused_adam_`` per group, as ``torch.optim.adam._fused_adam`` does), the others take ``step()``.
    The same update to the bit; what it saves is ``Optimizer.step``'s wrappers, ~0.15 ms per call on
    a CPU, with seven optimisers a step (docs/DESIGN.md, "torch's fused Adam called directly")."""
    groups, steps = [], []
    for opt in optimizers:
        if opt is None:
            continue
        ready = _fused_ready(opt)
        if ready is None:
            opt.step()
            continue
        groups += ready
        steps += [count for *_, counts in ready for count in counts]
    if not groups:
        return
    torch._foreach_add_(steps, 1)
    for group, params, grads, avgs, squares, counts in groups:
        beta1, beta2 = group["betas"]
        torch._fused_adam_(
            params, grads, avgs, squares, [], counts, amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2,
            weight_decay=group["weight_decay"], eps=group["eps"], maximize=False,
        )  # fmt: skip


def _fused_ready(opt: torch.optim.Optimizer) -> list | None:
    """Per group of ``opt``: (group, its parameters with a gradient, their gradients, exp_avgs,
    exp_avg_sqs, step counts), where ``step_adams`` may call the fused kernel itself (a fused, plain
    Adam whose every such parameter has its state, all on one device in one dtype); else None."""
    if type(opt) is not torch.optim.Adam:
        return None
    ready = []
    for group in opt.param_groups:
        if (
            not group.get("fused")
            or group["amsgrad"]
            or group["maximize"]
            or group.get("decoupled_weight_decay")
        ):
            return None
        if any(isinstance(v, torch.Tensor) for v in (group["lr"], *group["betas"])):
            return None
        params = [p for p in group["params"] if p.grad is not None]
        states = [opt.state.get(p) for p in params]
        if any(not s or "exp_avg" not in s for s in states):
            return None  # (the first step makes the state)
        if len({(p.device, p.dtype) for p in params}) > 1:
            return None
        if params:
            ready.append(
                (group, params, [p.grad for p in params], [s["exp_avg"] for s in states],
                 [s["exp_avg_sq"] for s in states], [s["step"] for s in states])
            )  # fmt: skip
    return ready


def zero_grads(optimizers: list[torch.optim.Optimizer | None]) -> None:
    """``opt.zero_grad(set_to_none=True)`` for each of ``optimizers`` (None skipped), without its wrappers."""
    for opt in optimizers:
        if opt is not None:
            for group in opt.param_groups:
                for p in group["params"]:
                    p.grad = None


def colour_optimizer(colour: nn.Module | None, cfg) -> torch.optim.Optimizer | None:
    """Adam for the per-camera colours (``models/colour.py``), trained in both stages; None without."""
    return None if colour is None else torch.optim.Adam(colour.parameters(), lr=cfg.colour_lr, eps=1e-15)


def field_lrs(cfg, extent: float, dynamic_step: int, dynamic_total: int) -> dict[str, float]:
    """Learning rate of every field group at this step of the dynamic stage (exponential decay)."""
    frac = dynamic_step / max(dynamic_total, 1)
    return {
        "fields": log_interp(cfg.field_lr, cfg.field_lr_final, frac),
        "grid": log_interp(cfg.grid_lr * extent, cfg.grid_lr_final * extent, frac),
    }


def set_group_lrs(opt: torch.optim.Optimizer | None, lrs: dict[str, float]) -> None:
    """Set each group's rate by its name (groups restored from an older checkpoint have none: "fields")."""
    if opt is not None:
        for group in opt.param_groups:
            group["lr"] = lrs[group.get("name", "fields")]


def set_lr(opt: torch.optim.Optimizer | None, lr: float) -> None:
    if opt is not None:
        for group in opt.param_groups:
            group["lr"] = lr


def means_lr(cfg, extent: float, step: int, total: int) -> float:
    return log_interp(cfg.means_lr * extent, cfg.means_lr_final * extent, step / max(total, 1))
