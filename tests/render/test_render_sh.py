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
