"""Spherical harmonics: basis values against closed forms, and SH colours through the renderer."""

from __future__ import annotations

import math

import pytest
import torch
from render_helpers import native_available

from tracegs.render import rasterize, sh_basis
from tracegs.render.random_scene import random_scene
from tracegs.render.sh import SH_C0, eval_sh_colors


def test_sh_basis_matches_closed_forms():
    dirs = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    x, y, z = dirs.unbind(-1)
    b = sh_basis(3, dirs)
    assert b.shape == (50, 16)
    # Real spherical harmonics written from their textbook definitions.
    torch.testing.assert_close(b[:, 0], torch.full_like(x, 0.5 * math.sqrt(1 / math.pi)))
    torch.testing.assert_close(b[:, 2], math.sqrt(3 / (4 * math.pi)) * z)  # Y_1^0
    torch.testing.assert_close(b[:, 6], 0.25 * math.sqrt(5 / math.pi) * (3 * z * z - 1))  # Y_2^0
    torch.testing.assert_close(b[:, 12], 0.25 * math.sqrt(7 / math.pi) * z * (5 * z * z - 3))  # Y_3^0
    # lower degrees are prefixes of higher ones
    torch.testing.assert_close(sh_basis(1, dirs), b[:, :4])


def test_sh_uses_only_first_coefficients_and_clamps():
    sc = random_scene(20, 16, 16, sh_degree=3)
    c1 = eval_sh_colors(sc["means"], sc["colors"], sc["viewmat"], 1)
    c1_trunc = eval_sh_colors(sc["means"], sc["colors"][:, :4], sc["viewmat"], 1)
    torch.testing.assert_close(c1, c1_trunc)
    dark = torch.full_like(sc["colors"][:, :1], -5.0)
    assert torch.all(eval_sh_colors(sc["means"], dark, sc["viewmat"], 0) == 0)


@pytest.mark.parametrize("backend", ["reference", "native"])
def test_degree0_sh_equals_rgb_path(backend):
    if backend == "native" and not native_available():
        pytest.skip("native extension not available")
    sc = random_scene(200, 24, 20, seed=5, sh_degree=0, scale=0.08)
    rgb = SH_C0 * sc["colors"][:, 0] + 0.5
    assert torch.all(rgb >= 0)  # no clamping, so both paths are the same function
    common = {k: v for k, v in sc.items() if k not in ("colors", "sh_degree")}
    out_sh = rasterize(**common, colors=sc["colors"], sh_degree=0, backend=backend)
    out_rgb = rasterize(**common, colors=rgb, backend=backend)
    assert out_sh.alpha.max() > 0.5
    torch.testing.assert_close(out_sh.image, out_rgb.image, atol=1e-6, rtol=0)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_native_sh_matches_reference_values_and_gradients(degree):
    """The C++ SH colours (the native backend's) against eval_sh_colors in float64: the colours, and
    the gradients of a random weighting of them to the coefficients (K beyond the degree's: zero)
    and, through the view direction, to the means; a share of the colours is clamped at 0."""
    if not native_available():
        pytest.skip("native extension not available")
    from tracegs.render.native import sh_colors_native

    g = torch.Generator().manual_seed(degree)
    n = 3000  # above the kernel's threshold for threads
    means = torch.randn(n, 3, generator=g, dtype=torch.float64) * 2
    coeffs = torch.randn(n, 16, 3, generator=g, dtype=torch.float64) * 1.5
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    viewmat[:3, 3] = torch.tensor([0.3, -0.2, 4.0], dtype=torch.float64)
    weights = torch.randn(n, 3, generator=g, dtype=torch.float64)
    grads = {}
    for name, dtype in (("reference", torch.float64), ("native", torch.float32)):
        m = means.to(dtype).clone().requires_grad_()
        c = coeffs.to(dtype).clone().requires_grad_()
        fn = eval_sh_colors if name == "reference" else sh_colors_native
        colors = fn(m, c, viewmat.to(dtype), degree)
        (colors.double() * weights).sum().backward()
        m_grad = torch.zeros_like(means) if m.grad is None else m.grad.double()  # degree 0: no path
        grads[name] = (colors.detach().double(), m_grad, c.grad.double())
    (ref_c, ref_m, ref_k), (nat_c, nat_m, nat_k) = grads["reference"], grads["native"]
    clamped = (ref_c == 0).double().mean()
    assert 0.05 < clamped < 0.6
    torch.testing.assert_close(nat_c, ref_c, atol=2e-6, rtol=1e-5)
    torch.testing.assert_close(nat_k, ref_k, atol=2e-6, rtol=1e-5)
    assert torch.all(nat_k[:, (degree + 1) ** 2 :] == 0)
    if degree == 0:
        assert torch.all(nat_m == 0)  # a constant colour has no direction
    else:
        assert ref_m.abs().max() > 1e-2
        torch.testing.assert_close(nat_m, ref_m, atol=2e-5, rtol=1e-4)


def test_native_sh_rejects_what_the_reference_rejects():
    if not native_available():
        pytest.skip("native extension not available")
    from tracegs.render.native import sh_colors_native

    with pytest.raises(ValueError, match="sh_degree=2"):
        sh_colors_native(torch.zeros(4, 3), torch.zeros(4, 4, 3), torch.eye(4), 2)
    with pytest.raises(ValueError, match="0..3"):
        sh_colors_native(torch.zeros(4, 3), torch.zeros(4, 25, 3), torch.eye(4), 4)
