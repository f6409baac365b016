"""The fields' native glue ops (csrc/mlp_cpu.cpp): the positional encoding and f_defo's output applied
to the Gaussians, against the ATen ops they replace and against closed forms / finite differences."""

from __future__ import annotations

import math

import pytest
import torch

from tracegs.models import deformation, encoding, fused_mlp

pytestmark = pytest.mark.skipif(fused_mlp.EXTENSION.load() is None, reason="the extension did not build here")


def encode(u: torch.Tensor, frequencies: int, include_input: bool, native: bool) -> torch.Tensor:
    previous, encoding.NATIVE = encoding.NATIVE, native
    try:
        return encoding.positional_encoding(u, frequencies, include_input)
    finally:
        encoding.NATIVE = previous


@pytest.mark.parametrize(
    "shape, frequencies, include_input",
    [
        ((3500, 3), 8, True),
        ((257, 1), 6, True),
        ((1, 1), 6, True),
        ((40, 4), 3, False),
        ((5, 2, 3), 5, True),
        ((0, 3), 4, True),
    ],
)
def test_native_encoding_matches_aten(shape, frequencies, include_input):
    u = torch.empty(shape).uniform_(-3, 3, generator=torch.Generator().manual_seed(0))
    ours, theirs = encode(u, frequencies, include_input, True), encode(u, frequencies, include_input, False)
    assert ours.shape == theirs.shape
    torch.testing.assert_close(ours, theirs, rtol=0, atol=4e-7)


def test_native_encoding_against_closed_form_and_beyond_its_reduction():
    """sin and cos against double precision, for angles up to 2^9 x 300 (past the fast reduction's
    range, where the op computes them one by one)."""
    u = torch.tensor([[0.0, 1e-3, -0.7, 2.5, 300.0, -123.4]]).T
    out = encode(u, 10, True, True).double()
    for row, value in enumerate(u[:, 0].double().tolist()):
        expected = [value]
        for k in range(10):
            angle = float(torch.tensor(value * 2.0**k, dtype=torch.float32))  # the float32 angle, exact
            expected += [math.sin(angle), math.cos(angle)]
        torch.testing.assert_close(out[row], torch.tensor(expected, dtype=torch.float64), rtol=0, atol=5e-7)


def test_native_encoding_gradient():
    g = torch.Generator().manual_seed(1)
    u = torch.empty(64, 3).uniform_(-2, 2, generator=g)
    weights = torch.randn(64, 3 * 13, generator=g)
    grads = []
    for native in (True, False):
        leaf = u.clone().requires_grad_()
        (encode(leaf, 6, True, native) * weights).sum().backward()
        grads.append(leaf.grad)
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-5, atol=1e-5)
    # and a finite difference of the native op itself, in one input
    h, row = 1e-2, 5
    shifted = [u.clone(), u.clone()]
    shifted[0][row, 1] += h
    shifted[1][row, 1] -= h
    numeric = ((encode(shifted[0], 6, True, True) - encode(shifted[1], 6, True, True)) * weights).sum() / (
        2 * h
    )
    assert abs(float(numeric) - float(grads[0][row, 1])) < 2e-2 * max(1.0, abs(float(numeric)))


def canonical_and_outputs(dtype, n: int, moved: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=g, dtype=dtype), dim=-1)
    canonical = [
        torch.randn(n, 3, generator=g, dtype=dtype),
        quats,
        torch.randn(n, 3, generator=g, dtype=dtype),
    ]
    outputs = [torch.randn(moved, c, generator=g, dtype=dtype) for c in (3, 4, 3)]
    return canonical, outputs


def deform(canonical, rows, outputs, native: bool):
    previous, deformation.NATIVE_DEFORM = deformation.NATIVE_DEFORM, native
    try:
        return deformation.deform_rows(canonical, rows, *outputs)
    finally:
        deformation.NATIVE_DEFORM = previous


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("with_rows", [True, False])
def test_native_deformation_matches_pytorch(dtype, with_rows):
    n = 60
    rows = torch.tensor([3, 7, 9, 20, 59, 0]) if with_rows else None
    canonical, outputs = canonical_and_outputs(dtype, n, 6 if with_rows else n)
    if with_rows:
        outputs[1][2] = 0.0  # a zero quaternion: the norm's clamp
    g = torch.Generator().manual_seed(2)
    weights = [torch.randn(n, c, generator=g, dtype=dtype) for c in (3, 4, 3)]
    results = []
    for native in (True, False):
        leaves = [t.clone().requires_grad_() for t in canonical + outputs]
        moved = deform(leaves[:3], rows, leaves[3:], native)
        sum((m * w).sum() for m, w in zip(moved, weights, strict=True)).backward()
        results.append([m.detach() for m in moved] + [leaf.grad for leaf in leaves])
    tolerance = 1e-12 if dtype == torch.float64 else 1e-6
    for ours, theirs in zip(*results, strict=True):
        scale = max(1.0, float(theirs.abs().max()))
        torch.testing.assert_close(ours, theirs, rtol=0, atol=tolerance * scale)
    if with_rows:  # the rows not moved are the canonical ones
        kept = torch.ones(n, dtype=torch.bool)
        kept[rows] = False
        for ours, c in zip(results[0][:3], canonical, strict=True):
            assert torch.equal(ours[kept], c[kept])


def test_native_deformation_gradients_match_finite_differences():
    rows = torch.tensor([1, 4, 5, 8])
    canonical, outputs = canonical_and_outputs(torch.float64, 10, 4, seed=3)
    leaves = [t.clone().requires_grad_() for t in canonical + outputs]
    assert torch.autograd.gradcheck(lambda *a: deform(list(a[:3]), rows, list(a[3:]), True), leaves)
