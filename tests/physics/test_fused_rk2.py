"""The native RK2 (physics/fused.py) against the PyTorch sub-steps it replaces, and its own gradients
against finite differences."""

from __future__ import annotations

import pytest
import torch

from tracegs.physics import fused
from tracegs.physics.integrate import DynamicsParams, integrate, integrate_rows, integrate_states
from tracegs.physics.so3 import quat_normalize

pytestmark = pytest.mark.skipif(fused.EXTENSION.load() is None, reason="the native RK2 did not build here")


def particles(n: int, dtype=torch.float64, seed: int = 0) -> list[torch.Tensor]:
    """x, q (unit) and v, w, a, e of ``n`` particles; the first few turn by less than the small-angle
    switch of ``axis_angle_to_quat`` in a sub-step, one not at all."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 3, generator=g, dtype=dtype)
    q = quat_normalize(torch.randn(n, 4, generator=g, dtype=dtype))
    v, w, a, e = (s * torch.randn(n, 3, generator=g, dtype=dtype) for s in (1.0, 3.0, 1.0, 2.0))
    w[:4] *= 1e-4
    e[:4] *= 1e-4
    w[4], e[4] = 0.0, 0.0
    return [x, q, v, w, a, e]


def run(tensors: list[torch.Tensor], enabled: bool, rotate: bool, duration: float, dt_max: float):
    """integrate's outputs and the gradients of a fixed random functional of them (x, q, params)."""
    inputs = [t.clone().requires_grad_() for t in tensors]
    x, q, *params = inputs
    previous, fused.ENABLED = fused.ENABLED, enabled
    try:
        x_end, q_end, params_end = integrate(
            x, q if rotate else None, DynamicsParams(*params), duration, dt_max, method="rk2"
        )
    finally:
        fused.ENABLED = previous
    g = torch.Generator().manual_seed(1)
    outputs = [x_end, *params_end[:2]] + ([q_end] if rotate else [])
    total = sum((o * torch.randn(o.shape, generator=g, dtype=o.dtype)).sum() for o in outputs)
    wrt = [t for i, t in enumerate(inputs) if rotate or i != 1]
    return outputs + list(torch.autograd.grad(total, wrt))


@pytest.mark.parametrize("rotate", [True, False])
@pytest.mark.parametrize("duration", [0.05, -0.05, 0.01])
def test_native_rk2_matches_the_pytorch_substeps(rotate, duration):
    tensors = particles(200)
    ours = run(tensors, True, rotate, duration, 1 / 59)
    reference = run(tensors, False, rotate, duration, 1 / 59)
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


def test_native_rk2_in_float32_agrees_to_rounding():
    tensors = particles(300, dtype=torch.float32)
    for a, b in zip(
        run(tensors, True, True, 0.05, 1 / 59), run(tensors, False, True, 0.05, 1 / 59), strict=True
    ):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_native_rk2_gradients_match_finite_differences():
    x, q, v, w, a, e = particles(6)
    inputs = [t.clone().requires_grad_() for t in (x, q, v, w, a, e)]
    assert torch.autograd.gradcheck(lambda *t: fused.fused_rk2(t[0], t[1], t[2:], 0.02, 3), inputs)
    assert torch.autograd.gradcheck(
        lambda *t: fused.fused_rk2(t[0], None, t[1:], -0.02, 2)[0], inputs[:1] + inputs[2:]
    )


def test_long_chains_with_gradients_fall_back_and_agree():
    tensors = particles(20)
    steps = fused.MAX_STEPS + 6
    ours = run(tensors, True, True, steps * 0.01, 0.01)  # over MAX_STEPS: the PyTorch path
    reference = run(tensors, False, True, steps * 0.01, 0.01)
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    with torch.no_grad():  # without gradients there is no replay, and no limit
        x, q, *params = tensors
        native = integrate(x, q, DynamicsParams(*params), steps * 0.01, 0.01)
        fused.ENABLED = False
        try:
            torch_path = integrate(x, q, DynamicsParams(*params), steps * 0.01, 0.01)
        finally:
            fused.ENABLED = True
    torch.testing.assert_close(native[0], torch_path[0], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(native[1], torch_path[1], rtol=1e-10, atol=1e-10)


def test_third_order_and_other_schemes_keep_the_pytorch_path():
    x, q, v, w, a, e = particles(5)
    assert fused.applies(x, q, DynamicsParams(v, w, a, e), 3)
    assert not fused.applies(x, q, DynamicsParams(v, w, a, e, a, e), 3)  # jerk terms
    assert not fused.applies(x.float(), q, DynamicsParams(v, w, a, e), 3)  # mixed dtypes


@pytest.mark.parametrize("method", ["rk2", "euler"])
def test_integrate_states_is_integrates_positions_and_orientations(method):
    x, q, *params = particles(40)
    ours = integrate_states(x, q, DynamicsParams(*params), 0.05, 1 / 59, method=method)
    reference = integrate(x, q, DynamicsParams(*params), 0.05, 1 / 59, method=method)[:2]
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    x_only = integrate_states(x, None, DynamicsParams(*params), -0.03, 1 / 59, method=method)
    assert x_only[1] is None
    torch.testing.assert_close(
        x_only[0], integrate(x, None, DynamicsParams(*params), -0.03, 1 / 59, method)[0]
    )


def run_rows(tensors, rows, enabled: bool, straight_through: bool, dtype=torch.float64):
    """``integrate_rows`` on the rows ``rows`` of the particles (the params those rows'): its outputs
    and the gradients of a fixed random functional of the full state (x, q, params)."""
    x, q, *params = [t.to(dtype).clone().requires_grad_() for t in tensors]
    rows_params = [p[rows].detach().requires_grad_() for p in params]
    previous, fused.ENABLED = fused.ENABLED, enabled
    try:
        x_end, q_end, moved = integrate_rows(
            x, q, rows, DynamicsParams(*rows_params), 0.05, 1 / 59, "rk2", straight_through
        )
    finally:
        fused.ENABLED = previous
    g = torch.Generator().manual_seed(2)
    total = sum((o * torch.randn(o.shape, generator=g, dtype=o.dtype)).sum() for o in (x_end, q_end))
    assert not moved.requires_grad
    return [x_end, q_end, moved, *torch.autograd.grad(total, [x, q, *rows_params])]


@pytest.mark.parametrize("straight_through", [True, False])
def test_native_rk2_of_some_rows_matches_gathers_and_copies(straight_through):
    """The rows' op (gathers, RK2 and copies back in one node) against the PyTorch gathers, index copies
    and straight-through sum it replaces: values and every gradient, the kept rows' included."""
    tensors = particles(200)
    rows = torch.randperm(200, generator=torch.Generator().manual_seed(3))[:120]
    ours = run_rows(tensors, rows, True, straight_through)
    reference = run_rows(tensors, rows, False, straight_through)
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    kept = torch.ones(200, dtype=torch.bool)
    kept[rows] = False
    assert torch.equal(ours[0][kept], tensors[0][kept]) and torch.equal(ours[1][kept], tensors[1][kept])
    d_x = ours[3]
    if straight_through:  # the positions' gradient passes to x unchanged, moved rows or not
        g = torch.Generator().manual_seed(2)
        assert torch.equal(d_x, torch.randn(ours[0].shape, generator=g, dtype=d_x.dtype))


def test_native_rk2_of_some_rows_gradients_match_finite_differences():
    x, q, v, w, a, e = particles(9)
    rows = torch.tensor([7, 0, 3, 4])
    inputs = [x.clone().requires_grad_(), q.clone().requires_grad_()] + [
        p[rows].clone().requires_grad_() for p in (v, w, a, e)
    ]
    assert torch.autograd.gradcheck(
        lambda *t: fused.fused_rk2_rows(t[0], t[1], rows, t[2:], 0.02, 3, False)[:2], inputs
    )


def test_rows_with_a_gradient_to_the_state_only_fall_back_beyond_the_replay_limit():
    """Params without a gradient but a quaternion with one: over MAX_STEPS the rows take the PyTorch
    path (the native backward replays at most MAX_STEPS sub-steps)."""
    x, q, v, w, a, e = particles(10)
    rows = torch.tensor([1, 4, 6])
    params = DynamicsParams(*(p[rows] for p in (v, w, a, e)))
    steps = fused.MAX_STEPS + 1
    assert fused.applies_rows(x, q, rows, params, fused.MAX_STEPS)
    assert not fused.applies_rows(x, q.clone().requires_grad_(), rows, params, steps)
    assert fused.applies_rows(x, q, rows, params, steps)
    q = q.clone().requires_grad_()
    _, q_end, _ = integrate_rows(x, q, rows, params, steps * 0.01, 0.01)
    q_end.sum().backward()
    assert torch.isfinite(q.grad).all()
