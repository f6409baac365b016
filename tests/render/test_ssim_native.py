"""The native SSIM of the training loss (render/ssim.py) against pytorch-msssim's (image_metrics.ssim)
and against finite differences."""

import pytest
import torch

from tracegs.image_metrics import ssim
from tracegs.render.ssim import EXTENSION, training_ssim

pytestmark = pytest.mark.skipif(EXTENSION.load() is None, reason="the C++ extension does not build here")


def _pair(h=40, w=33, noise=0.1, seed=0):
    g = torch.Generator().manual_seed(seed)
    target = torch.rand(h, w, 3, generator=g, dtype=torch.float64).float()
    image = (target + noise * torch.randn(h, w, 3, generator=g)).clamp(0, 1)
    return image.requires_grad_(), target


@pytest.mark.parametrize(("h", "w", "noise"), [(40, 33, 0.1), (11, 11, 0.3), (64, 128, 0.02)])
def test_native_ssim_equals_pytorch_msssim_in_value_and_gradient(h, w, noise):
    image, target = _pair(h, w, noise)
    expected = ssim(image, target)
    (grad_expected,) = torch.autograd.grad(expected, image)
    value = training_ssim(image, target)
    (grad,) = torch.autograd.grad(3.0 * value, image)  # the upstream gradient is applied
    assert value.item() == pytest.approx(expected.item(), abs=2e-6)
    peak = 3.0 * grad_expected.abs().max().item()  # float32 sums in another order: to the largest
    assert torch.allclose(grad, 3.0 * grad_expected, rtol=1e-4, atol=1e-5 * peak)


def test_native_ssim_gradient_matches_finite_differences():
    image, target = _pair(16, 14, 0.2, seed=3)
    x = image.detach().double()
    (grad,) = torch.autograd.grad(training_ssim(image, target), image)
    g = torch.Generator().manual_seed(1)
    for _ in range(6):
        i, j, c = (int(torch.randint(n, (1,), generator=g)) for n in (16, 14, 3))
        eps = 1e-3
        up, down = x.clone(), x.clone()
        up[i, j, c] += eps
        down[i, j, c] -= eps
        numeric = (ssim(up, target.double()) - ssim(down, target.double())) / (2 * eps)
        assert grad[i, j, c].item() == pytest.approx(numeric.item(), rel=2e-3, abs=1e-7)


def test_identical_images_have_ssim_one_and_other_inputs_fall_back():
    image, target = _pair()
    assert training_ssim(target.clone().requires_grad_(), target).item() == pytest.approx(1.0, abs=1e-6)
    double = training_ssim(image.detach().double().requires_grad_(), target.double())
    assert double.dtype == torch.float64  # not the float32 kernel: image_metrics.ssim
    assert training_ssim(image, target, native=False).item() == pytest.approx(ssim(image, target).item())


def test_native_ssim_is_the_same_on_any_thread_count():
    image, target = _pair(64, 48)
    previous = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2, 3):
            torch.set_num_threads(threads)
            value = training_ssim(image, target)
            results.append((value.detach(), torch.autograd.grad(value, image)[0]))
    finally:
        torch.set_num_threads(previous)
    for value, grad in results[1:]:
        assert torch.equal(value, results[0][0]) and torch.equal(grad, results[0][1])
