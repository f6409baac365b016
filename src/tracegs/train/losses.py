"""The photometric loss of 3DGS and TRACE: (1 - w) * L1 + w * (1 - SSIM), w = 0.2."""

from __future__ import annotations

import torch

from ..render.ssim import training_ssim


def photometric_loss(
    image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2
) -> dict[str, torch.Tensor]:
    """Named loss terms for a rendered ``image`` [H, W, 3] against ``target`` [H, W, 3]; "loss" is the sum.
    SSIM is ``image_metrics.ssim``'s, by the native kernel on the CPU (``render/ssim.py``)."""
    l1 = (image - target).abs().mean()
    s = training_ssim(image, target)
    return {"l1": l1, "ssim": s.detach(), "loss": (1 - ssim_weight) * l1 + ssim_weight * (1 - s)}
