"""rasterize(): output contract, backend selection, and the gsplat backend (CUDA only)."""

from __future__ import annotations

import pytest
import torch
from render_helpers import PARAMS, hard_scene, native_available, rel_err, render_with_grads

from tracegs.render import RenderResult, available_backends, rasterize
from tracegs.render.random_scene import random_scene


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
    gpu = {k: v.cpu() for k, v in gpu.items()}
    # Which Gaussians count as visible differs at the margins: gsplat >= 1.5 culls by a per-axis,
    # opacity-aware box (docs/RASTERIZER.md), we by a square 3-sigma one. Those that only one side
    # keeps touch the image at most beyond 3 sigma (alpha <= 0.011 opacity): small gradients.
    differ = (gpu["radii"] > 0) != (cpu["radii"] > 0)
    touch = {
        side: r["grad_opacities"][differ].abs().max().item() / r["grad_opacities"].abs().max().item()
        for side, r in (("gsplat", gpu), ("cpu", cpu))
        if differ.any()
    }
    # gsplat's tile binning (3 or 3.33 sigma depending on version) may drop a few pixels where a
    # Gaussian's alpha is barely above 1/255, so compare with a tolerance of a few such alphas.
    errors = {f"{key} max": (gpu[key] - cpu[key]).abs().max().item() for key in ("image", "alpha")}
    errors |= {f"{key} mean": (gpu[key] - cpu[key]).abs().mean().item() for key in ("image", "alpha")}
    grads = {name: rel_err(gpu["grad_" + name], cpu["grad_" + name]) for name in [*PARAMS, "means2d"]}
    report = f"visibility differs for {int(differ.sum())}: {touch}; images {errors}; gradients {grads}"
    assert differ.float().mean() < 0.02 and all(v < 1e-2 for v in touch.values()), report
    assert all(v < (2e-2 if "max" in k else 1e-4) for k, v in errors.items()), report
    # Measured on an H200 with gsplat 1.5.3 (2026-11-26): images 2.1e-3 max / 6.5e-6 mean; gradients
    # <= 4.3e-4 except means2d 2.9e-3 and opacities 2.9e-2. The opacities' gradient is the loosest:
    # the loss's depth term divides by alpha, which amplifies the threshold pixels above.
    assert all(v < (5e-2 if name == "opacities" else 2e-2) for name, v in grads.items()), report


def test_gsplat_without_loadable_kernels_is_not_available(monkeypatch):
    """A gsplat that imports but whose CUDA kernels do not load (no nvcc, a failed build) is not
    offered: one warning, and ``auto`` renders CUDA tensors with the reference backend."""
    import sys
    import types

    from tracegs.render import gsplat_backend

    broken = types.ModuleType("gsplat.cuda._backend")
    broken._C = None  # what gsplat leaves when it finds no CUDA toolkit
    for name, module in {
        "gsplat": types.ModuleType("gsplat"),
        "gsplat.cuda": types.ModuleType("gsplat.cuda"),
        "gsplat.cuda._backend": broken,
    }.items():
        monkeypatch.setitem(sys.modules, name, module)
    gsplat_backend.is_available.cache_clear()
    try:
        with pytest.warns(RuntimeWarning, match="could not be loaded.*reference"):
            assert not gsplat_backend.is_available()
        assert not gsplat_backend.is_available()  # asked once: no second build, no second warning
    finally:
        gsplat_backend.is_available.cache_clear()
