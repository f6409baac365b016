"""The C++ backend must reproduce the pure-PyTorch reference: images, gradients, determinism."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch
from render_helpers import PARAMS, hard_scene, native_available, rel_err, render_with_grads

from tracegs.machine import this_machine
from tracegs.render import native
from tracegs.render.rendering import resolve_backend

CASES = {
    # name: (gaussians, width, height, sh_degree, background)
    "odd_size": (300, 37, 29, None, None),
    "multi_tile": (1500, 70, 52, None, (0.2, 0.5, 0.9)),
    "sh3": (400, 45, 33, 3, None),
}


@pytest.fixture(scope="module", params=list(CASES))
def pair(request):
    if not native_available():
        pytest.skip("native extension not available")
    n, w, h, sh, bg = CASES[request.param]
    scene = hard_scene(n, w, h, seed=len(request.param), sh_degree=sh)
    background = None if bg is None else torch.tensor(bg)
    ref = render_with_grads(scene, "reference", background=background)
    nat = render_with_grads(scene, "native", background=background)
    return ref, nat


def test_images_match(pair):
    ref, nat = pair
    assert torch.equal(ref["radii"], nat["radii"])
    assert (ref["radii"] > 0).sum() > 10 and (ref["radii"] == 0).sum() > 0  # some culled, many not
    for key in ("image", "alpha"):
        assert (ref[key] - nat[key]).abs().max() < 1e-5, key
    scale = ref["depth"].abs().max()
    assert (ref["depth"] - nat["depth"]).abs().max() < 1e-5 * scale
    assert ref["alpha"].max() > 0.9  # the scene is not empty


@pytest.mark.parametrize("name", [*PARAMS, "means2d"])
def test_gradients_match(pair, name):
    ref, nat = pair
    g_ref, g_nat = ref["grad_" + name], nat["grad_" + name]
    assert g_ref is not None and g_nat is not None
    assert g_ref.abs().max() > 0
    assert rel_err(g_nat, g_ref) < 1e-4, name


def test_culled_gaussians_get_no_gradient(pair):
    _, nat = pair
    culled = nat["radii"] == 0
    assert torch.all(nat["grad_means"][culled] == 0)
    assert torch.all(nat["grad_means2d"][culled] == 0)
    assert torch.all(nat["means2d"][culled] == 0)


def test_gradients_deterministic_across_thread_counts():
    if not native_available():
        pytest.skip("native extension not available")
    scene = hard_scene(3000, 96, 64, seed=3)
    before = torch.get_num_threads()
    try:
        runs = []
        for threads in (1, 2, 2):
            torch.set_num_threads(threads)
            runs.append(render_with_grads(scene, "native"))
    finally:
        torch.set_num_threads(before)
    for other in runs[1:]:
        for key in ("image", *("grad_" + p for p in PARAMS), "grad_means2d"):
            assert torch.equal(runs[0][key], other[key]), key


NARROWER_BUILD = {"avx512f": ("x86-64-v3", "avx2"), "avx2": ("x86-64", "sse")}
"""A CPU's narrower vector width to build the rasteriser for: (``TRACEGS_MARCH``, what it has)."""


def test_narrower_vector_build_gives_the_same_bits(tmp_path):
    """The blending runs a tile row as vectors of the build's own width (1 x AVX-512, 2 x AVX2, 4 x SSE):
    every lane computes the same operations, so a narrower build renders the same bits."""
    if not native_available():
        pytest.skip("native extension not available")
    flags = this_machine().flags
    narrower = next((NARROWER_BUILD[f] for f in NARROWER_BUILD if f in flags), None)
    if narrower is None:
        pytest.skip("not an x86 CPU with AVX2 or AVX-512")
    march, _ = narrower
    scene = hard_scene(3000, 70, 52, seed=5, sh_degree=1)
    torch.save(scene, tmp_path / "scene.pt")
    script = (
        "import sys, torch; sys.path.insert(0, sys.argv[1]); from render_helpers import render_with_grads; "
        "torch.save(render_with_grads(torch.load(sys.argv[2]), 'native'), sys.argv[3])"
    )
    env = {**os.environ, "TRACEGS_MARCH": march}
    args = [sys.executable, "-c", script, str(Path(__file__).parent), str(tmp_path / "scene.pt")]
    subprocess.run([*args, str(tmp_path / "out.pt")], env=env, check=True, timeout=600)
    other, here = torch.load(tmp_path / "out.pt"), render_with_grads(scene, "native")
    assert other["image"].abs().max() > 0
    for key in ("image", "alpha", "depth", *("grad_" + p for p in PARAMS), "grad_means2d"):
        assert torch.equal(here[key], other[key]), key


def test_build_failure_falls_back_to_reference_with_one_warning(monkeypatch):
    def broken(openmp):
        raise RuntimeError("simulated compiler failure")

    monkeypatch.setattr(native.EXTENSION, "module", None)
    monkeypatch.setattr(native.EXTENSION, "error", None)
    monkeypatch.setattr(native.EXTENSION, "build", broken)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert resolve_backend("auto", torch.device("cpu")) == "reference"
        assert resolve_backend("auto", torch.device("cpu")) == "reference"
    msgs = [str(w.message) for w in caught if "native CPU rasteriser" in str(w.message)]
    assert len(msgs) == 1 and "simulated compiler failure" in msgs[0]
    with pytest.raises(RuntimeError):
        resolve_backend("native", torch.device("cpu"))
