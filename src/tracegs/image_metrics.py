"""Image metrics and image files, shared by every layer that needs them (data generation, training
losses, the post-training calibration, evaluation): MSE, PSNR, MAE-PSNR, SSIM, and reading an image
file. LPIPS, which needs network weights, lives in ``eval/lpips.py``.

Every metric takes images [..., H, W, 3] with values in [0, 1] and returns one value per image, keeping
the batch dimensions. ``docs/METRICS.md`` defines each metric and how the TRACE paper aggregates them.
"""

# H/W: image height/width; "...": any batch dimensions (frames, cameras)

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from pytorch_msssim import ssim as _msssim_ssim

__all__ = [
    "SSIM_SIGMA",
    "SSIM_WINDOW",
    "as_rgba",
    "load_image",
    "mae_psnr",
    "mse",
    "psnr",
    "read_image_array",
    "ssim",
]

SSIM_WINDOW = 11
"""Side of the Gaussian SSIM window (Wang et al. 2004); images smaller than this are rejected."""
SSIM_SIGMA = 1.5
"""Standard deviation of the Gaussian SSIM window, in pixels."""


def _check_pair(img: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    img, ref = torch.broadcast_tensors(img, ref)
    if img.ndim < 3 or img.shape[-1] != 3:
        raise ValueError(f"expected RGB images [..., H, W, 3], got shape {tuple(img.shape)}")
    return img, ref


def mse(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean squared error per image: [..., H, W, 3] x2 -> [...]."""
    img, ref = _check_pair(img, ref)
    return ((img - ref) ** 2).mean(dim=(-3, -2, -1))


def psnr(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR in dB per image with peak value 1: ``-10 log10(MSE)``; [..., H, W, 3] x2 -> [...].

    Identical images give ``inf``. Averaging this over frames is the "mean of PSNRs"; the TRACE paper
    reports :func:`mae_psnr` instead.
    """
    return -10.0 * torch.log10(mse(img, ref))


def mae_psnr(mses: Sequence[float] | torch.Tensor) -> float:
    """PSNR of the mean MSE over frames, ``10 log10(1 / mean(MSE))``, as the TRACE paper reports it.

    Differs from the mean of per-frame PSNRs (Jensen): frames with large errors weigh more.
    """
    values = torch.as_tensor(mses, dtype=torch.float64).reshape(-1)
    if values.numel() == 0:
        raise ValueError("mae_psnr needs at least one MSE value")
    if bool((values < 0).any()) or not bool(torch.isfinite(values).all()):
        raise ValueError("MSE values must be finite and non-negative")
    return float(-10.0 * torch.log10(values.mean()))


def ssim(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """SSIM per image (Wang et al. 2004) on RGB in [0, 1]: [..., H, W, 3] x2 -> [...]; differentiable.

    11x11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, computed by pytorch-msssim:
    "valid" filtering (no padding), SSIM map averaged over pixels then over the three channels. This equals
    scikit-image's ``structural_similarity(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
    data_range=1, channel_axis=-1)``. Images smaller than the window in either side raise ``ValueError``
    (pytorch-msssim would silently skip the smoothing along that side).
    """
    img, ref = _check_pair(img, ref)
    batch, (h, w) = img.shape[:-3], img.shape[-3:-1]
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {h}x{w}")
    if not img.is_floating_point():
        raise TypeError(f"SSIM expects floating-point images in [0, 1], got {img.dtype}")
    x = img.reshape(-1, h, w, 3).permute(0, 3, 1, 2)
    y = ref.reshape(-1, h, w, 3).permute(0, 3, 1, 2).to(x.dtype)
    value = _msssim_ssim(x, y, data_range=1.0, size_average=False, win_size=SSIM_WINDOW, win_sigma=SSIM_SIGMA)
    return value.reshape(batch)


def read_image_array(path: str | Path) -> np.ndarray:
    """The pixels of an image file as imageio decodes them ([H, W] or [H, W, C], any dtype).

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file for one that is
    empty, truncated or not an image (imageio blames those on a missing plugin; the file is the cause).
    """
    import imageio.v3 as iio

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: image not found")
    if path.stat().st_size == 0:
        raise ValueError(f"{path}: empty file (0 bytes), not an image")
    try:
        return np.asarray(iio.imread(path))
    except Exception as e:  # imageio raises many types depending on the plugin
        detail = " ".join(str(e).split()[:12])
        raise ValueError(f"{path}: truncated or not an image ({type(e).__name__}: {detail})") from None


def to_unit_range(array: np.ndarray, path: str | Path) -> np.ndarray:
    """Pixels as float32 in [0, 1]: 8- and 16-bit integers divided by their maximum, floats as they are."""
    if np.issubdtype(array.dtype, np.integer):
        return array.astype(np.float32) / float(np.iinfo(array.dtype).max)
    if np.issubdtype(array.dtype, np.floating) or array.dtype == np.bool_:
        return array.astype(np.float32)
    raise ValueError(f"{path}: unsupported pixel type {array.dtype}")


def as_rgba(array: np.ndarray, path: str | Path) -> np.ndarray:
    """[H, W, 4] float32 in [0, 1] from grey, grey + alpha, RGB or RGBA pixels (alpha 1 where none)."""
    array = to_unit_range(array, path)
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[-1] not in (1, 2, 3, 4):
        raise ValueError(f"{path}: unsupported image shape {array.shape} (animated or multi-page?)")
    channels = array.shape[-1]
    color = array[..., :3] if channels >= 3 else np.repeat(array[..., :1], 3, axis=-1)
    alpha = array[..., -1:] if channels in (2, 4) else np.ones_like(array[..., :1])
    return np.concatenate([color, alpha], axis=-1)


def load_image(path: str | Path, background: Sequence[float] = (1.0, 1.0, 1.0)) -> torch.Tensor:
    """Read an image file -> [H, W, 3] float32 in [0, 1].

    8- and 16-bit integer images are divided by their maximum; grey images are repeated to RGB; an alpha
    channel is composited over ``background`` (white by default, like the Blender/D-NeRF test images).
    Raises ``FileNotFoundError`` / ``ValueError`` naming the file if it is missing or cannot be decoded.
    """
    rgba = as_rgba(read_image_array(path), path)
    alpha = rgba[..., 3:]
    color = rgba[..., :3] * alpha + np.asarray(background, dtype=np.float32) * (1.0 - alpha)
    return torch.from_numpy(np.array(color, dtype=np.float32))  # a fresh, writable copy
