"""Image-quality metrics of the evaluation: those of ``tracegs.image_metrics`` (MSE, PSNR, MAE-PSNR,
SSIM), the SSIM map that a masked SSIM averages, LPIPS, and a comparer of two image files.
"""

from __future__ import annotations

import importlib
from pathlib import Path

import torch

from ..image_metrics import SSIM_SIGMA, SSIM_WINDOW, load_image, mae_psnr, mse, psnr, ssim
from . import lpips as _lpips

_msssim = importlib.import_module("pytorch_msssim.ssim")  # (the package's name `ssim` is its function)

__all__ = [
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "compare_images",
    "load_image",
    "mae_psnr",
    "mse",
    "psnr",
    "ssim",
    "ssim_map",
]


def ssim_map(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """The SSIM map whose mean is ``ssim``: [H, W, 3] x2 -> [H - 10, W - 10], the SSIM of the window
    centred on each pixel whose whole window lies inside the image (pixel (i + 5, j + 5) at [i, j]),
    averaged over the three channels. Same window (11x11 Gaussian, sigma 1.5), constants (K1 = 0.01,
    K2 = 0.03, data range 1) and "valid" filtering as ``ssim``, whose value is this map's mean."""
    if img.shape != ref.shape or img.ndim != 3 or img.shape[-1] != 3:
        raise ValueError(
            f"expected two RGB images [H, W, 3] of one size, got {tuple(img.shape)}, {tuple(ref.shape)}"
        )
    h, w = img.shape[:2]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {h}x{w}")
    x, y = img.permute(2, 0, 1)[None], ref.permute(2, 0, 1)[None].to(img.dtype)  # [1, 3, H, W]
    # pytorch-msssim's own window and "valid" separable filter, as ``ssim`` computes with them
    win = _msssim._fspecial_gauss_1d(SSIM_WINDOW, SSIM_SIGMA).repeat(3, 1, 1, 1).to(x)

    def blur(z: torch.Tensor) -> torch.Tensor:
        return _msssim.gaussian_filter(z, win)

    c1, c2 = 0.01**2, 0.03**2
    mu_x, mu_y = blur(x), blur(y)
    var_x, var_y = blur(x * x) - mu_x**2, blur(y * y) - mu_y**2
    cov = blur(x * y) - mu_x * mu_y
    value = ((2 * mu_x * mu_y + c1) / (mu_x**2 + mu_y**2 + c1)) * ((2 * cov + c2) / (var_x + var_y + c2))
    return value[0].mean(dim=0)


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
