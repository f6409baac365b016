"""The HexPlane's native CPU kernels against their definitions (grid_sample, PyTorch total variation)."""

import pytest
import torch

from tracegs.models import hexplane
from tracegs.models.hexplane import (
    PLANES,
    HexPlane,
    HexPlaneConfig,
    plane_tv,
    plane_tv_reference,
    sample_plane,
)
from tracegs.train.optim import field_optimizer

pytestmark = pytest.mark.skipif(hexplane.EXTENSION.load() is None, reason="C++ extension not built")


def random_planes(channels=5, spatial=(7, 9), time=4, seed=0):
    """Six channels-last planes [1, C, res_j, res_i] with the HexPlane's axis order."""
    gen = torch.Generator().manual_seed(seed)
    res = [spatial[0], spatial[1], spatial[0] + 2, time]  # x, y, z, t: all sizes differ
    planes = []
    for i, j in PLANES:
        plane = 0.5 + torch.rand(1, channels, res[j], res[i], generator=gen)
        planes.append(plane.contiguous(memory_format=torch.channels_last).requires_grad_())
    return planes


def reference_product(planes, coords):
    product = 1.0
    for (i, j), plane in zip(PLANES, planes, strict=True):
        product = product * sample_plane(plane, coords[:, [i, j]])
    return product


def random_coords(n=300, seed=1):
    coords = torch.rand(n, 4, generator=torch.Generator().manual_seed(seed)) * 2 - 1
    return coords


def test_product_of_samples_and_its_gradients_equal_grid_sample():
    planes = random_planes()
    coords = random_coords().requires_grad_()
    out = hexplane.product_of_samples(planes, coords)
    expected = reference_product(planes, coords)
    torch.testing.assert_close(out, expected, rtol=1e-5, atol=1e-6)
    upstream = torch.randn_like(out)
    grads = torch.autograd.grad(out, [coords, *planes], upstream)
    expected_grads = torch.autograd.grad(expected, [coords, *planes], upstream)
    for got, want in zip(grads, expected_grads, strict=True):
        torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-5)
    assert all(g.abs().sum() > 0 for g in grads)


def test_coordinates_on_or_beyond_the_border_read_the_border_with_zero_gradient():
    planes = random_planes(channels=3)
    coords = torch.tensor([[1.0, -1.0, 0.2, 0.3], [1.7, -3.0, 0.2, 0.3]], requires_grad=True)
    out = hexplane.product_of_samples(planes, coords)
    torch.testing.assert_close(out[0], out[1])
    torch.testing.assert_close(out, reference_product(planes, coords))
    (grad,) = torch.autograd.grad(out.sum(), coords)
    assert (grad[:, :2] == 0).all() and (grad[:, 2:] != 0).all()
    (want,) = torch.autograd.grad(reference_product(planes, coords).sum(), coords)
    torch.testing.assert_close(grad, want)


def test_coordinate_gradient_matches_finite_differences():
    planes = [p.detach() for p in random_planes(channels=2)]
    coords = torch.tensor([[0.13, -0.41, 0.52, -0.27]])
    (grad,) = torch.autograd.grad(hexplane.product_of_samples(planes, coords.requires_grad_()).sum(), coords)
    eps = 1e-3
    for k in range(4):
        step = torch.zeros(1, 4)
        step[0, k] = eps
        with torch.no_grad():
            up = hexplane.product_of_samples(planes, coords + step).sum()
            down = hexplane.product_of_samples(planes, coords - step).sum()
        assert abs(float(grad[0, k]) - float(up - down) / (2 * eps)) < 2e-3 * max(1.0, abs(float(grad[0, k])))


def test_kernels_give_the_same_bits_on_one_and_two_threads():
    planes = random_planes()
    coords = random_coords(500).requires_grad_()
    results = []
    before = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out = hexplane.product_of_samples(planes, coords)
            tv = sum(plane_tv(p, 0.7) for p in planes)
            grads = torch.autograd.grad(out.square().sum() + tv, [coords, *planes])
            results.append((out, tv, *grads))
    finally:
        torch.set_num_threads(before)
    for a, b in zip(*results, strict=True):
        assert torch.equal(a, b)


@pytest.mark.parametrize("shape", [(1, 4, 5, 7), (1, 32, 25, 64), (1, 3, 2, 33)])
def test_total_variation_and_its_gradient_equal_the_definition(shape):
    gen = torch.Generator().manual_seed(3)
    plane = torch.rand(*shape, generator=gen).contiguous(memory_format=torch.channels_last).requires_grad_()
    for scale, upstream in ((1.0, 1.0), (0.25, -3.0)):
        value = plane_tv(plane, scale)
        expected = scale * plane_tv_reference(plane)
        torch.testing.assert_close(value, expected, rtol=1e-5, atol=1e-7)
        (grad,) = torch.autograd.grad(value * upstream, plane)
        (want,) = torch.autograd.grad(expected * upstream, plane)
        torch.testing.assert_close(grad, want, rtol=1e-5, atol=1e-9)


def test_grid_keeps_channels_last_planes_and_reads_a_contiguous_state_dict():
    cfg = HexPlaneConfig(spatial_resolution=6, time_resolution=5, feature_dim=4)
    grid = HexPlane(cfg)
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in grid.parameters())
    with torch.no_grad():
        for p in grid.parameters():
            p.uniform_(0.5, 1.5)
    # a checkpoint written with ordinary (channels-first) planes loads into the same function
    state = {k: v.contiguous() for k, v in grid.state_dict().items()}
    other = HexPlane(cfg)
    other.load_state_dict(state)
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in other.parameters())
    x, t = torch.rand(50, 3) * 2 - 1, torch.rand(50, 1)
    torch.testing.assert_close(other(x, t), grid(x, t))
    # and the native path computes what grid_sample computes on the same planes
    native = other(x, t)
    hexplane.EXTENSION.module, saved = None, hexplane.EXTENSION.module
    hexplane.EXTENSION.error = "disabled for the test"
    try:
        fallback = other(x, t)
    finally:
        hexplane.EXTENSION.module, hexplane.EXTENSION.error = saved, None
    torch.testing.assert_close(native, fallback, rtol=1e-5, atol=1e-6)


def test_field_optimizer_is_fused_on_the_cpu_and_makes_the_plain_adam_update():
    gen = torch.Generator().manual_seed(4)
    weights = [torch.randn(6, 5, generator=gen) for _ in range(2)]
    grads = [[torch.randn(6, 5, generator=gen) for _ in range(2)] for _ in range(5)]

    class Cfg:
        field_lr = 1e-2

    results = []
    for fused in (True, False):
        params = [torch.nn.Parameter(w.clone()) for w in weights]
        if fused:
            opt = field_optimizer({"fields": params[:1], "grid": params[1:]}, Cfg)
            assert opt.defaults["fused"]
        else:
            opt = torch.optim.Adam(params, lr=Cfg.field_lr, eps=1e-15)
        for step in grads:
            for p, g in zip(params, step, strict=True):
                p.grad = g.clone()
            opt.step()
        results.append(params)
    for a, b, w in zip(*results, weights, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
        assert (a - w).abs().mean() > 1e-2  # five Adam steps of lr 1e-2 moved the weights
