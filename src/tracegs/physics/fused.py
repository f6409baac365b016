"""The midpoint RK2 of ``integrate.py`` as one native op on the CPU (``csrc/rk2_cpu.cpp``).

``integrate(method="rk2")`` takes this path by itself where it applies (a CPU, float32/float64, a
second-order system, quaternions or positions only) and the extension builds; elsewhere, and with
``ENABLED = False``, it runs the PyTorch sub-steps. Both compute the same formulas in the same order:
values and gradients agree to float rounding (tests/physics/test_fused_rk2.py).

A training step's other small physics ops as one autograd node each: the RK2 of the moving rows of
the full state tensors with their gathers and copies back (``fused_rk2_rows``, from
``integrate.integrate_rows``), and the second-order acceleration consistency
(``second_order_consistency``). Each had ~10 ATen ops and autograd nodes of a few microseconds, run
on one thread while the other waits (docs/DESIGN.md, "The fields' glue as native ops").

N: particles; M: the rows moved.
"""

from __future__ import annotations

import torch

from ..cpp import EXTENSIONS

EXTENSION = EXTENSIONS["tracegs_rk2_cpu"]

ENABLED = True
"""Use the native op where it applies (set False to compare with the PyTorch path)."""
MAX_STEPS = 64
"""Sub-steps the backward replays per particle (``csrc/rk2_cpu.cpp``); more fall back to PyTorch."""


def applies(x: torch.Tensor, q: torch.Tensor | None, params, steps: int) -> bool:
    """Whether ``fused_rk2`` can integrate these (``params``: a ``DynamicsParams``)."""
    if not ENABLED or params.jerk is not None or x.device.type != "cpu" or x.dim() != 2:
        return False
    if x.dtype not in (torch.float32, torch.float64) or (q is not None and q.shape != (x.shape[0], 4)):
        return False
    tensors = [x, *params[:4]] + ([q] if q is not None else [])
    if any(t.dtype != x.dtype or t.device != x.device or t.shape[0] != x.shape[0] for t in tensors):
        return False
    needs_grad = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
    if needs_grad and steps > MAX_STEPS:
        return False
    return EXTENSION.load() is not None


class _FusedRK2(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, q, v, w, a, e, dt: float, steps: int):
        rotate = q is not None
        ops = EXTENSION.load()
        args = [t.contiguous() for t in (x, q if rotate else x, v, w, a, e)]
        x_out, q_out = ops.rk2_forward(*args, dt, steps, rotate)
        ctx.save_for_backward(*args)
        ctx.settings = (dt, steps, rotate)
        ctx.set_materialize_grads(False)  # an unused output's gradient stays None (see backward)
        return (x_out, q_out) if rotate else (x_out, None)

    @staticmethod
    def backward(ctx, gx, gq):
        dt, steps, rotate = ctx.settings
        x, q, v, w, a, e = ctx.saved_tensors
        used_x, used_q = gx is not None, rotate and gq is not None
        gx = torch.zeros_like(x) if gx is None else gx
        gq = (torch.zeros_like(q) if gq is None else gq) if rotate else gx
        grads = EXTENSION.load().rk2_backward(gx, gq, x, q, v, w, a, e, dt, steps, rotate)
        # the end position does not depend on q, nor the end orientation on x: no gradient, not zeros
        reaches = [used_x, used_q, True, True, True, True]
        needed = ctx.needs_input_grad[:6]
        return (*[g if r and n else None for g, r, n in zip(grads, reaches, needed, strict=True)], None, None)


class _FusedRK2Rows(torch.autograd.Function):
    """The RK2 of some rows of full state tensors, the gathers and scatters inside: one autograd node
    instead of ~10 (two gathers, two index copies, the straight-through sum and their backwards)."""

    @staticmethod
    def forward(ctx, x, q, rows, v, w, a, e, dt: float, steps: int, straight_through: bool):
        ops = EXTENSION.load()
        x_rows, q_rows = x.detach().index_select(0, rows), q.detach().index_select(0, rows)
        args = [x_rows, q_rows, *[t.detach().contiguous() for t in (v, w, a, e)]]
        x_end, q_end = ops.rk2_forward(*args, dt, steps, True)
        ctx.save_for_backward(rows, *args)
        ctx.settings = (dt, steps, straight_through)
        ctx.mark_non_differentiable(x_end)
        return x.detach().index_copy(0, rows, x_end), q.detach().index_copy(0, rows, q_end), x_end

    @staticmethod
    def backward(ctx, gx, gq, _):
        dt, steps, straight_through = ctx.settings
        rows, *args = ctx.saved_tensors
        g_rows = (gx.index_select(0, rows), gq.index_select(0, rows))
        gx0, gq0, gv, gw, ga, ge = EXTENSION.load().rk2_backward(*g_rows, *args, dt, steps, True)
        d_x = gx if straight_through else gx.index_copy(0, rows, gx0)
        return d_x, gq.index_copy(0, rows, gq0), None, gv, gw, ga, ge, None, None, None


def applies_rows(x: torch.Tensor, q: torch.Tensor, rows: torch.Tensor, params, steps: int) -> bool:
    """Whether ``fused_rk2_rows`` can integrate the rows ``rows`` of ``x`` [N, 3] and ``q`` [N, 4]
    (``params``: those rows', as ``applies`` takes them; a gradient to ``x`` or ``q`` counts too)."""
    if rows.dim() != 1 or rows.dtype != torch.int64 or rows.device != x.device or x.dim() != 2:
        return False
    if q.shape != (x.shape[0], 4) or any(
        t.dtype != params.velocity.dtype or t.device != x.device for t in (x, q)
    ):
        return False
    needs_grad = torch.is_grad_enabled() and (x.requires_grad or q.requires_grad)
    return applies(params.velocity, None, params, steps) and not (needs_grad and steps > MAX_STEPS)


def fused_rk2_rows(
    x: torch.Tensor,
    q: torch.Tensor,
    rows: torch.Tensor,
    params,
    dt: float,
    steps: int,
    straight_through: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``fused_rk2`` of the rows ``rows`` (distinct indices) of ``x`` [N, 3] and ``q`` [N, 4], ``params``
    [M, 3] for those rows: ``(x, q)`` [N, ...] with those rows moved and the others kept, and the moved
    rows' positions [M, 3] (no gradient). ``straight_through``: the motion starts from ``x`` detached and
    the positions' gradient passes to ``x`` unchanged (``integrate.integrate_rows``). Call where
    ``applies_rows`` says so."""
    v, w, a, e = params[:4]
    return _FusedRK2Rows.apply(x, q, rows, v, w, a, e, float(dt), int(steps), bool(straight_through))


def fused_rk2(
    x: torch.Tensor, q: torch.Tensor | None, params, dt: float, steps: int
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``steps`` midpoint-RK2 sub-steps of ``dt`` from ``x`` [N, 3] and ``q`` [N, 4] (or None: positions
    only) with ``params`` (velocities and their rates, order 2) at the start: ``(x, q)`` at the end.
    Call where ``applies`` says so."""
    v, w, a, e = params[:4]
    return _FusedRK2.apply(x, q, v, w, a, e, float(dt), int(steps))


class _SecondOrderConsistency(torch.autograd.Function):
    """``acceleration_consistency`` without jerks as one autograd node (a training step's ~12 small ops
    each had theirs): the gap ``(|v + s a - v_later|.mean() + |w + s e - w_later|.mean()) / |s|`` and
    its gradient to the accelerations, ``sign(.) * (g / |s| / count) * s``, in the same order of
    operations as autograd's, hence the same bits."""

    @staticmethod
    def forward(ctx, a, e, v, w, v_later, w_later, s: float):
        gap, signs = consistency_gap(a, e, v, w, v_later, w_later, s)
        ctx.save_for_backward(*signs)
        ctx.s = s
        return gap

    @staticmethod
    def backward(ctx, grad):
        return *consistency_grads(ctx.saved_tensors, grad, ctx.s), None, None, None, None, None


def consistency_gap(a, e, v, w, v_later, w_later, s: float) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """The second-order consistency's gap and the signs its gradient reads, autograd's operations in
    autograd's order (``_SecondOrderConsistency``; ``models/fields_step.py``)."""
    gaps = [v + s * a - v_later, w + s * e - w_later]
    return (gaps[0].abs().mean() + gaps[1].abs().mean()) / abs(s), [torch.sign(g) for g in gaps]


def consistency_grads(signs, grad: torch.Tensor, s: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The gap's gradient ``grad`` as the accelerations' ``(d a, d e)``, from ``consistency_gap``'s signs."""
    per = grad / abs(s) / signs[0].numel()
    return signs[0] * per * s, signs[1] * per * s


def second_order_consistency(a, e, v, w, v_later, w_later, s: float) -> torch.Tensor:
    """``integrate.acceleration_consistency`` of a second-order system (``v``, ``w``, ``v_later``,
    ``w_later`` held fixed) as one autograd node, the same bits."""
    return _SecondOrderConsistency.apply(a, e, v, w, v_later, w_later, float(s))
