"""rasterize(): output contract, backend selection, and the gsplat backend (CUDA only)."""

from __future__ import annotations

import pytest
import torch
from render_helpers import PARAMS, hard_scene, native_available, rel_err, render_with_grads

from tracegs.render import RenderResult, available_backends, rasterize
from tracegs.render.bench import random_scene


@pytest.mark.parametrize("backend", ["reference", "native"])
def test_output_shapes_and_means2d_grad(backend):
    if backend == "native" and not native_available():
        pytest.skip("native extension not available")
    sc = random_scene(100, 24, 17, seed=1, scale=0.08)
    means = sc.pop("means").requires_grad_(True)
    out = rasterize(means, **sc, backend=backend, background=torch.tensor([1.0, 1.0, 1.0]))
    assert isinstance(out, RenderResult) and out.backend == backend
    assert (
        out.image.shape == (17, 24, 3) and out.alpha.shape == (17, 24, 1) and out.depth.shape == (17, 24, 1)
    )
    assert out.means2d.shape == (100, 2) and out.radii.shape == (100,)
    assert not out.radii.dtype.is_floating_point
    # a white background shows through where alpha < 1
    assert torch.all(out.image >= (1 - out.alpha) - 1e-6)
    out.image.mean().backward()
    assert out.means2d.grad is not None and out.means2d.grad.abs().sum() > 0
    assert means.grad is not None


def test_backend_selection():
    names = available_backends("cpu")
    assert "reference" in names and "gsplat" not in names
    sc = random_scene(10, 16, 16)
    out = rasterize(**sc)
    assert out.backend == ("native" if native_available() else "reference")
    with pytest.raises(ValueError):
        rasterize(**sc, backend="nope")
    with pytest.raises(ValueError):
        rasterize(**sc, backend="gsplat")


@pytest.mark.parametrize("backend", ["reference", "native"])
def test_empty_scene(backend):
    if backend == "native" and not native_available():
        pytest.skip("native extension not available")
    sc = random_scene(0, 20, 10)
    out = rasterize(**sc, backend=backend, background=torch.tensor([0.5, 0.5, 0.5]))
    assert torch.all(out.alpha == 0) and torch.allclose(out.image, torch.full((10, 20, 3), 0.5))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="gsplat backend needs CUDA")
def test_gsplat_matches_cpu_backends():
    pytest.importorskip("gsplat")
    scene = hard_scene(2000, 64, 48, seed=11, sh_degree=2)
    cpu = render_with_grads(scene, "native" if native_available() else "reference")
    cuda_scene = {k: (v.cuda() if torch.is_tensor(v) else v) for k, v in scene.items()}
    gpu = render_with_grads(cuda_scene, "gsplat")
    assert torch.equal(gpu["radii"].cpu() > 0, cpu["radii"] > 0)
    # gsplat's tile binning (3 or 3.33 sigma depending on version) may drop a few pixels where a
    # Gaussian's alpha is barely above 1/255, so compare with a tolerance of a few such alphas.
    for key in ("image", "alpha"):
        assert (gpu[key].cpu() - cpu[key]).abs().max() < 2e-2, key
        assert (gpu[key].cpu() - cpu[key]).abs().mean() < 1e-4, key
    for name in [*PARAMS, "means2d"]:
        assert rel_err(gpu["grad_" + name].cpu(), cpu["grad_" + name]) < 2e-2, name
