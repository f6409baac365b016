"""SSIM for the training loss on the CPU: one C++ kernel for the forward and one for the backward
(``csrc/ssim_cpu.cpp``), the same function as ``image_metrics.ssim`` (pytorch-msssim).

pytorch-msssim filters each of its five moment maps with two depthwise convolutions and lets autograd
run them backwards: about 20 small kernels and their temporaries per image, ~3.7 ms forward + backward
at 128 x 128 on one core of the Xeon host, an eighth of a training step. The kernel here does the
separable filtering in plain loops, keeps the three partial maps the backward needs and filters them
once with the transposed window (``benchmarks/training_speed.py`` measures both). Elsewhere (CUDA, other dtypes,
no compiler) ``image_metrics.ssim`` runs.
"""

from __future__ import annotations

import torch

from ..cpp import EXTENSIONS
from ..image_metrics import ssim

EXTENSION = EXTENSIONS["tracegs_ssim_cpu"]


class _NativeSSIM(torch.autograd.Function):
    @staticmethod
    def forward(ctx, image: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
        value, partials = EXTENSION.module.ssim_forward(image, target)
        ctx.save_for_backward(image, target, partials)
        return value

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        image, target, partials = ctx.saved_tensors
        return EXTENSION.module.ssim_backward(image, target, partials, float(grad)), None


def training_ssim(image: torch.Tensor, target: torch.Tensor, native: bool = True) -> torch.Tensor:
    """Mean SSIM of ``image`` [H, W, 3] against ``target`` [H, W, 3] (differentiable in ``image``): the
    native kernel for float32 CPU images when it builds (``native``), else ``image_metrics.ssim``."""
    use = (
        native
        and image.device.type == "cpu"
        and image.dtype == target.dtype == torch.float32
        and image.dim() == 3
        and image.shape[-1] == 3
        and image.shape == target.shape
        and not target.requires_grad
        and min(image.shape[:2]) >= 11
        and EXTENSION.load() is not None
    )
    return _NativeSSIM.apply(image, target.detach()) if use else ssim(image, target)
