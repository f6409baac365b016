"""The fields' MLPs as one native op forward and one backward on the CPU (``csrc/mlp_cpu.cpp``).

``DeformationField`` and ``DynamicsField`` take this path by themselves where it applies (``applies``:
a CPU, float32 or float64 fields, more than one point, the extension built with AVX2 or AVX-512) and, with
``ENABLED = False``, run their PyTorch layers. Both compute the same function: values and gradients
agree to float rounding (tests/models/test_fused_mlp.py).

Under bf16 autocast the op multiplies in bf16 where it was built for AVX512-BF16 (``bf16_products``:
the forward's and the input gradients' products from bf16 operands with float sums, the weights'
gradients in float32, as autocast's layers but for the last), except on CPUs with AMX tiles, where
autocast's oneDNN products keep the fields.

N: points, E: input channels, O: a layer's outputs.
"""

from __future__ import annotations

import contextlib
import functools

import torch

from ..cpp import EXTENSIONS
from ..utils import cpu_flags
from .encoding import fold_single_rows

EXTENSION = EXTENSIONS["tracegs_mlp_cpu"]

ENABLED = True
"""Use the native op where it applies (set False to compare with the PyTorch layers)."""

ACTIVATION_CODES = {"relu": 0, "silu": 1}

MIN_VECTOR_BYTES = 32
"""The fields take the op where it was built with vectors at least this wide: AVX-512 or AVX2, where
it beats ATen's layers (docs/DESIGN.md, "Fused MLPs"); an SSE or NEON build is not measured."""


def applies(x: torch.Tensor) -> bool:
    """Whether ``fused_mlp`` serves the encoded inputs ``x`` [N, E]: float32 or float64 on the CPU,
    with the extension built for vectors of ``MIN_VECTOR_BYTES``; under bf16 autocast where the op has
    ``bf16_products``."""
    if not ENABLED or x.device.type != "cpu" or x.dim() != 2 or x.shape[0] < 2:
        return False
    if x.dtype not in (torch.float32, torch.float64):
        return False
    if _autocast_bf16() and (x.dtype != torch.float32 or not bf16_products()):
        return False
    return _vector_bytes() >= MIN_VECTOR_BYTES


def _autocast_bf16() -> bool:
    return torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu") == torch.bfloat16


@functools.cache
def bf16_products() -> bool:
    """Whether the op serves bf16 autocast here: built for AVX512-BF16, on a CPU without AMX tiles
    (there oneDNN's tile products are the measured path; docs/DESIGN.md, "bf16 fields")."""
    ops = EXTENSION.load()
    return ops is not None and bool(ops.bf16_products()) and "amx_bf16" not in cpu_flags()


@functools.cache
def _vector_bytes() -> int:
    """The built op's vector width in bytes (0 where it did not build)."""
    ops = EXTENSION.load()
    return 0 if ops is None else int(ops.vector_bytes())


class _FusedMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, skip_weight, settings, *layers):
        skip_layer, activation, last_activation, _, bf16 = settings
        half = len(layers) // 2
        weights, biases = list(layers[:half]), list(layers[half:])
        saved = EXTENSION.load().mlp_forward(
            x, weights, biases, skip_weight, skip_layer, activation, last_activation, bf16
        )
        ctx.save_for_backward(skip_weight, *weights, *saved[1:])  # x, z and h, padded
        ctx.settings, ctx.layers = settings, half
        return saved[0]

    @staticmethod
    @torch.autograd.function.once_differentiable  # (no second derivatives: a clear error, not zeros)
    def backward(ctx, grad_out):
        skip_layer, activation, last_activation, stop_from, bf16 = ctx.settings
        skip_weight, *rest = ctx.saved_tensors
        n = ctx.layers
        weights, saved = rest[:n], rest[n:]
        grads = EXTENSION.load().mlp_backward(
            grad_out.contiguous(),
            [grad_out, *saved],  # (slot 0, the output, is not read)
            weights,
            skip_weight,
            skip_layer,
            activation,
            last_activation,
            stop_from,
            ctx.needs_input_grad[0],
            bf16,
        )
        d_skip = grads[2 * n] if skip_weight is not None and ctx.needs_input_grad[1] else None
        d_x = grads[2 * n + 1] if ctx.needs_input_grad[0] else None
        return d_x, d_skip, None, *grads[:n], *grads[n : 2 * n]


def fused_mlp(
    x: torch.Tensor,
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    activation: str,
    last_activation: bool = False,
    skip: tuple[int, torch.Tensor] | None = None,
    stop_from: int | None = None,
) -> torch.Tensor:
    """The MLP ``z_i = in_i W_i^T + b_i``, ``h_i = act(z_i)`` on ``x`` [N, E] (``in_0 = x``,
    ``in_i = h_{i-1}``), the last layer linear unless ``last_activation``: its output [N, O_last].

    ``skip = (i, S)``: layer ``i`` also adds ``x S^T`` (a concatenation [x, h] with its weight split);
    ``stop_from``: the last layer's outputs from this one on pass no gradient to its input (they still
    train its weights). Call where ``applies`` says so; under bf16 autocast the products are bf16's
    (``bf16_products``)."""
    skip_layer, skip_weight = (-1, None) if skip is None else skip
    settings = (
        skip_layer,
        ACTIVATION_CODES[activation],
        last_activation,
        -1 if stop_from is None else stop_from,
        _autocast_bf16(),
    )
    return _FusedMLP.apply(x.contiguous(), skip_weight, settings, *weights, *biases)


def fold_parts(
    weight: torch.Tensor, bias: torch.Tensor, parts: list[tuple[torch.Tensor, slice | torch.Tensor]]
) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor]:
    """A first layer on parts of its input (``encoding.product_of_parts``' arguments) as the fused
    op's ``(x, weight, bias)``: the single-row parts (a time shared by every point) folded into the
    bias, the others concatenated with their weight columns. ``x`` is None when every part folded.

    The fold is a one-row product in float32 also under bf16 autocast: the op takes a float bias,
    and autocast's casts of the row, the columns and the bias (and their autograd nodes) cost more
    than the product."""
    with torch.autocast("cpu", enabled=False) if _autocast_bf16() else contextlib.nullcontext():
        bias, rows = fold_single_rows(weight, bias, parts)
    bias = bias.reshape(-1)
    if not rows:
        return None, None, bias
    if len(rows) == 1:
        return *rows[0], bias
    values, columns = zip(*rows, strict=True)
    return torch.cat(values, dim=-1), torch.cat(columns, dim=-1), bias
