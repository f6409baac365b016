"""PSNR / MSE / MAE-PSNR / SSIM on constructed images, and the image-file comparer."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tracegs.eval.metrics import compare_images
from tracegs.image_metrics import load_image, mae_psnr, mse, psnr, ssim


def _random_pair(*batch: int, h: int = 32, w: int = 40, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    img = torch.rand(*batch, h, w, 3, generator=g, dtype=torch.float64)
    noise = 0.1 * torch.randn(*batch, h, w, 3, generator=g, dtype=torch.float64)
    return img, (img + noise).clamp(0, 1)


# --- MSE / PSNR / MAE-PSNR ----------------------------------------------------------------------------


def test_constant_offset_gives_known_mse_and_psnr():
    ref = torch.full((8, 9, 3), 0.4, dtype=torch.float64)
    img = ref + 0.1
    assert mse(img, ref).item() == pytest.approx(0.01)
    assert psnr(img, ref).item() == pytest.approx(20.0)


def test_psnr_keeps_batch_dimensions():
    ref = torch.zeros(2, 3, 4, 5, 3)
    offsets = torch.tensor([[0.1, 0.01, 0.5], [0.2, 0.05, 1.0]])
    img = ref + offsets[:, :, None, None, None]
    expected = -20.0 * torch.log10(offsets)
    values = psnr(img, ref)
    assert values.shape == (2, 3)
    torch.testing.assert_close(values, expected)


def test_psnr_is_per_image_not_per_batch():
    ref = torch.zeros(2, 4, 4, 3)
    img = ref.clone()
    img[0] += 0.1
    img[1, 0, 0, 0] = 1.0  # one pixel: MSE 1/48
    torch.testing.assert_close(psnr(img, ref), torch.tensor([20.0, 10 * math.log10(48)]))


def test_mae_psnr_is_psnr_of_mean_mse_not_mean_of_psnrs():
    mses = [0.01, 0.0001]
    mean_of_psnrs = sum(-10 * math.log10(m) for m in mses) / len(mses)
    assert mean_of_psnrs == pytest.approx(30.0)
    assert mae_psnr(mses) == pytest.approx(10 * math.log10(1 / 0.00505))
    assert mae_psnr(torch.tensor(mses)) == pytest.approx(10 * math.log10(1 / 0.00505))
    assert mae_psnr(mses) < mean_of_psnrs - 7  # ~22.97 dB, far from 30


def test_mae_psnr_rejects_empty_and_negative():
    with pytest.raises(ValueError):
        mae_psnr([])
    with pytest.raises(ValueError):
        mae_psnr([0.01, -0.01])


def test_shape_check():
    with pytest.raises(ValueError, match="H, W, 3"):
        psnr(torch.zeros(4, 4), torch.zeros(4, 4))


# --- SSIM ---------------------------------------------------------------------------------------------


def test_ssim_of_identical_images_is_one():
    img, _ = _random_pair(2)
    torch.testing.assert_close(ssim(img, img), torch.ones(2, dtype=torch.float64))


def test_ssim_matches_pytorch_msssim():
    from pytorch_msssim import ssim as reference

    img, ref = _random_pair(3)
    expected = reference(
        img.permute(0, 3, 1, 2), ref.permute(0, 3, 1, 2), data_range=1.0, size_average=False, win_size=11
    )
    torch.testing.assert_close(ssim(img, ref), expected)
    assert (ssim(img, ref) < 0.99).all()


def test_ssim_matches_scikit_image():
    metrics = pytest.importorskip("skimage.metrics", reason="scikit-image not installed")
    img, ref = _random_pair(h=37, w=29, seed=3)
    expected = metrics.structural_similarity(
        img.numpy(),
        ref.numpy(),
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
        data_range=1.0,
        channel_axis=-1,
    )
    assert ssim(img, ref).item() == pytest.approx(expected, abs=1e-6)


def test_ssim_keeps_batch_dimensions():
    img, ref = _random_pair(2, 3, h=16, w=16)
    values = ssim(img, ref)
    assert values.shape == (2, 3)
    torch.testing.assert_close(values[1, 2], ssim(img[1, 2], ref[1, 2]))


def test_ssim_is_differentiable():
    img, ref = _random_pair(h=16, w=20)
    img = img.clone().requires_grad_(True)
    (1 - ssim(img, ref)).backward()
    assert img.grad is not None
    assert torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0


def test_ssim_rejects_images_smaller_than_the_window():
    img, ref = _random_pair(h=10, w=32)
    with pytest.raises(ValueError, match="at least 11x11"):
        ssim(img, ref)


# --- image files --------------------------------------------------------------------------------------


def _write(path, array):
    import imageio.v3 as iio

    iio.imwrite(path, array)
    return path


def test_load_image_composites_rgba_on_white(tmp_path):
    rgba = np.zeros((4, 5, 4), dtype=np.uint8)
    rgba[..., 0] = 255  # red
    rgba[:2, :, 3] = 255  # top half opaque, bottom half transparent
    image = load_image(_write(tmp_path / "a.png", rgba))
    assert image.shape == (4, 5, 3) and image.dtype == torch.float32
    torch.testing.assert_close(image[0, 0], torch.tensor([1.0, 0.0, 0.0]))
    torch.testing.assert_close(image[3, 0], torch.tensor([1.0, 1.0, 1.0]))
    black = load_image(tmp_path / "a.png", background=(0, 0, 0))
    torch.testing.assert_close(black[3, 0], torch.tensor([0.0, 0.0, 0.0]))


def test_load_image_grey_becomes_rgb(tmp_path):
    grey = np.full((3, 4), 51, dtype=np.uint8)
    image = load_image(_write(tmp_path / "g.png", grey))
    assert image.shape == (3, 4, 3)
    torch.testing.assert_close(image, torch.full((3, 4, 3), 0.2))


def test_compare_images_values(tmp_path):
    rng = np.random.default_rng(0)
    a = rng.integers(0, 256, (24, 20, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + 10, 0, 255).astype(np.uint8)
    pa, pb = _write(tmp_path / "a.png", a), _write(tmp_path / "b.png", b)
    result = compare_images(pa, pb, lpips=False)
    assert set(result) == {"psnr", "ssim"}
    assert all(isinstance(v, float) for v in result.values())
    expected = -10 * np.log10(np.mean(((a / 255.0) - (b / 255.0)) ** 2))
    assert result["psnr"] == pytest.approx(expected, abs=1e-4)
    assert compare_images(pa, pa, lpips=False)["ssim"] == pytest.approx(1.0)


def test_compare_images_names_missing_file(tmp_path):
    good = _write(tmp_path / "good.png", np.zeros((16, 16, 3), dtype=np.uint8))
    with pytest.raises(FileNotFoundError, match="missing.png"):
        compare_images(good, tmp_path / "missing.png", lpips=False)


def test_compare_images_names_corrupt_file(tmp_path):
    good = _write(tmp_path / "good.png", np.zeros((16, 16, 3), dtype=np.uint8))
    corrupt = tmp_path / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    with pytest.raises(ValueError, match="corrupt.png"):
        compare_images(corrupt, good, lpips=False)


def test_compare_images_rejects_size_mismatch(tmp_path):
    a = _write(tmp_path / "a.png", np.zeros((16, 16, 3), dtype=np.uint8))
    b = _write(tmp_path / "b.png", np.zeros((16, 18, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match=r"differ in size.*a\.png.*b\.png"):
        compare_images(a, b, lpips=False)
