"""Image-quality metrics of the evaluation: those of ``tracegs.image_metrics`` (MSE, PSNR, MAE-PSNR,
SSIM), LPIPS, and a comparer of two image files.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..image_metrics import SSIM_SIGMA, SSIM_WINDOW, load_image, mae_psnr, mse, psnr, ssim
from . import lpips as _lpips

__all__ = ["SSIM_SIGMA", "SSIM_WINDOW", "compare_images", "load_image", "mae_psnr", "mse", "psnr", "ssim"]


def compare_images(
    path_a: str | Path, path_b: str | Path, device: str | torch.device = "cpu", lpips: bool = True
) -> dict[str, float]:
    """PSNR, SSIM and (if ``lpips``) LPIPS-VGG / LPIPS-Alex between two image files.

    Returns ``{"psnr", "ssim", "lpips_vgg", "lpips_alex"}`` as floats (the LPIPS keys only if ``lpips``).
    RGBA images are composited on white. Raises ``ValueError`` naming both files if their sizes differ.
    """
    a = load_image(path_a).to(device)
    b = load_image(path_b).to(device)
    if a.shape != b.shape:
        raise ValueError(
            f"images differ in size: {path_a} is {a.shape[1]}x{a.shape[0]}, "
            f"{path_b} is {b.shape[1]}x{b.shape[0]}"
        )
    with torch.no_grad():
        result = {"psnr": float(psnr(a, b)), "ssim": float(ssim(a, b))}
        if lpips:
            result["lpips_vgg"] = float(_lpips.lpips(a, b, net="vgg"))
            result["lpips_alex"] = float(_lpips.lpips(a, b, net="alex"))
    return result
