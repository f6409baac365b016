"""Optimisers and learning-rate schedules (3DGS for the Gaussians, one Adam for both fields)."""

from __future__ import annotations

import torch
from torch import nn

from .strategy import log_interp


def gaussian_optimizers(params: nn.ParameterDict, cfg, extent: float) -> dict[str, torch.optim.Optimizer]:
    """One Adam per Gaussian parameter (densification replaces rows of each independently)."""
    lrs = {
        "means": cfg.means_lr * extent,
        "quats": cfg.quat_lr,
        "scales": cfg.scale_lr,
        "opacities": cfg.opacity_lr,
        "sh0": cfg.sh0_lr,
        "shN": cfg.shN_lr,
    }
    return {name: torch.optim.Adam([params[name]], lr=lrs[name], eps=1e-15) for name in params.keys()}


def field_optimizer(parameters: list[nn.Parameter], cfg) -> torch.optim.Optimizer | None:
    return torch.optim.Adam(parameters, lr=cfg.field_lr, eps=1e-15) if parameters else None


def set_lr(opt: torch.optim.Optimizer | None, lr: float) -> None:
    if opt is not None:
        for group in opt.param_groups:
            group["lr"] = lr


def means_lr(cfg, extent: float, step: int, total: int) -> float:
    return log_interp(cfg.means_lr * extent, cfg.means_lr_final * extent, step / max(total, 1))


def field_lr(cfg, dynamic_step: int, dynamic_total: int) -> float:
    return log_interp(cfg.field_lr, cfg.field_lr_final, dynamic_step / max(dynamic_total, 1))
