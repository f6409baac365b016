"""The midpoint RK2 of ``integrate.py`` as one native op on the CPU (``csrc/rk2_cpu.cpp``).

``integrate(method="rk2")`` takes this path by itself where it applies (a CPU, float32/float64, a
second-order system, quaternions or positions only) and the extension builds; elsewhere, and with
``ENABLED = False``, it runs the PyTorch sub-steps. Both compute the same formulas in the same order:
values and gradients agree to float rounding (tests/physics/test_fused_rk2.py).

N: particles.
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


def fused_rk2(
    x: torch.Tensor, q: torch.Tensor | None, params, dt: float, steps: int
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``steps`` midpoint-RK2 sub-steps of ``dt`` from ``x`` [N, 3] and ``q`` [N, 4] (or None: positions
    only) with ``params`` (velocities and their rates, order 2) at the start: ``(x, q)`` at the end.
    Call where ``applies`` says so."""
    v, w, a, e = params[:4]
    return _FusedRK2.apply(x, q, v, w, a, e, float(dt), int(steps))
