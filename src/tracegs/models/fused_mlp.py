"""The fields' MLPs as one native op forward and one backward on the CPU (``csrc/mlp_cpu.cpp``).

``DeformationField`` and ``DynamicsField`` take this path by themselves where it applies (``applies``:
a CPU, float32 or float64 fields, more than one point, the extension built with AVX2 or AVX-512) and, with
``ENABLED = False``, run their PyTorch layers. Both compute the same function: values and gradients
agree to float rounding (tests/models/test_fused_mlp.py).

Under bf16 autocast the op multiplies in bf16 where it was built for AVX512-BF16 (``bf16_products``:
every product from bf16 operands with float sums, as autocast's layers, whose weights' gradients are
also rounded to bf16 where these stay float), except on CPUs with AMX tiles, where autocast's oneDNN
products keep the fields.

N: points, E: input channels, O: a layer's outputs.
"""

from __future__ import annotations

import contextlib
import functools

import torch

from ..cpp import EXTENSIONS
from ..machine import this_machine
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
    if (
        x.device.type != "cpu"
        or x.dim() != 2
        or x.shape[0] < 2
        or x.dtype not in (torch.float32, torch.float64)
    ):
        return False
    bf16 = _autocast_bf16()
    return serves(bf16) and not (bf16 and x.dtype != torch.float32)


def serves(bf16: bool) -> bool:
    """Whether the op serves the fields here at all (``ENABLED``, built with vectors of
    ``MIN_VECTOR_BYTES``), with bf16 products where ``bf16`` (``bf16_products``)."""
    return ENABLED and _vector_bytes() >= MIN_VECTOR_BYTES and (not bf16 or bf16_products())


def _autocast_bf16() -> bool:
    return torch.is_autocast_enabled("cpu") and torch.get_autocast_dtype("cpu") == torch.bfloat16


@functools.cache
def bf16_products() -> bool:
    """Whether the op serves bf16 autocast here: built for AVX512-BF16, on a CPU without AMX tiles
    (there oneDNN's tile products are the measured path; docs/DESIGN.md, "bf16 fields")."""
    ops = EXTENSION.load()
    return ops is not None and bool(ops.bf16_products()) and "amx_bf16" not in this_machine().flags


@functools.cache
def _vector_bytes() -> int:
    """The built op's vector width in bytes (0 where it did not build)."""
    ops = EXTENSION.load()
    return 0 if ops is None else int(ops.vector_bytes())


class _FusedMLP(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, skip_weight, time_row, settings, *layers):
        skip_layer, activation, last_activation, _, bf16, encoded, groups, scaled_from, scale, save = settings
        half = len(layers) // 2
        weights, biases = list(layers[:half]), list(layers[half:])
        saved = EXTENSION.load().mlp_forward(
            x, weights, biases, skip_weight, skip_layer, activation, last_activation, bf16,
            time_row, encoded, groups, scaled_from, scale, save,
        )  # fmt: skip
        outputs = len(groups)
        if save:
            ctx.save_for_backward(skip_weight, time_row, *weights, *saved[outputs:])  # x, each layer's z or h
        ctx.settings, ctx.layers = settings, half
        return tuple(saved[:outputs])

    @staticmethod
    @torch.autograd.function.once_differentiable  # (no second derivatives: a clear error, not zeros)
    def backward(ctx, *grads_out):
        skip_layer, activation, last_activation, stop_from, bf16, encoded, _, scaled_from, scale, _ = (
            ctx.settings
        )
        skip_weight, time_row, *rest = ctx.saved_tensors
        n = ctx.layers
        weights, saved = rest[:n], rest[n:]
        grads = EXTENSION.load().mlp_backward(
            list(grads_out), saved, weights, skip_weight, skip_layer, activation, last_activation,
            stop_from, ctx.needs_input_grad[0], bf16, time_row, encoded, scaled_from, scale,
        )  # fmt: skip
        d_skip = grads[2 * n] if skip_weight is not None and ctx.needs_input_grad[1] else None
        d_x = grads[2 * n + 1] if ctx.needs_input_grad[0] else None
        return d_x, d_skip, None, None, *grads[:n], *grads[n : 2 * n]


def fused_mlp(
    x: torch.Tensor,
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    activation: str,
    last_activation: bool = False,
    skip: tuple[int, torch.Tensor | None] | None = None,
    stop_from: int | None = None,
    time_row: torch.Tensor | None = None,
    groups: tuple[int, ...] | None = None,
    scaled_from: int | None = None,
    scale: float = 1.0,
) -> torch.Tensor | tuple[torch.Tensor, ...]:
    """The MLP ``z_i = in_i W_i^T + b_i``, ``h_i = act(z_i)`` on ``x`` [N, E] (``in_0 = x``,
    ``in_i = h_{i-1}``), the last layer linear unless ``last_activation``: its output [N, O_last].

    ``skip = (i, S)``: layer ``i`` also adds ``x S^T`` (a concatenation [x, h] with its weight split);
    ``stop_from``: the last layer's outputs from this one on pass no gradient to its input (they still
    train its weights). ``time_row`` [1, Et] (no gradient): every point's input is ``[x, time_row]``,
    the first layer's weight whole [O, E + Et] and the row's product folded into its bias; the skip
    layer then has ``skip = (i, None)`` and its whole weight [O, E + Et + K] (the hidden input last).
    ``groups``: the output as a tuple of tensors of these column counts, those from column
    ``scaled_from`` on as ``r |r| / scale`` (f_trd's rates). Call where ``applies`` says so; under bf16
    autocast the products are bf16's (``bf16_products``)."""
    skip_layer, skip_weight = (-1, None) if skip is None else skip
    outputs = (weights[-1].shape[0],) if groups is None else tuple(groups)
    tensors = (x, skip_weight, *weights, *biases)
    # without a gradient to come (f_trd's second query, under no_grad) the op keeps no activations
    save = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)
    settings = (
        skip_layer,
        ACTIVATION_CODES[activation],
        last_activation,
        -1 if stop_from is None else stop_from,
        _autocast_bf16(),
        0 if time_row is None else weights[0].shape[1],
        outputs,
        -1 if scaled_from is None else scaled_from,
        float(scale),
        save,
    )
    out = _FusedMLP.apply(x.contiguous(), skip_weight, time_row, settings, *weights, *biases)
    return out[0] if groups is None else out


def fused_mlp_of_parts(
    parts: list[tuple[torch.Tensor, slice | torch.Tensor]],
    weights: list[torch.Tensor],
    biases: list[torch.Tensor],
    activation: str,
    skip_layer: int | None = None,
    **kwargs,
) -> torch.Tensor | tuple[torch.Tensor, ...]:
    """``fused_mlp`` on an input given in parts (``encoding.product_of_parts``' arguments), every
    weight whole: the first layer's takes the parts' concatenation [O, E], the skip layer's (index
    ``skip_layer``, >= 1) that concatenation then the previous layer's output [O, E + K].

    Where the parts are the points' own columns then one row shared by all (a frame's time) the op
    takes them as they are (``time_row``); otherwise they are folded and concatenated here
    (``fold_parts``). ``kwargs``: ``fused_mlp``'s ``stop_from``, ``groups``, ``scaled_from``, ``scale``."""
    weights, biases = list(weights), list(biases)
    shared = _points_then_row(parts)
    if shared is not None:
        x, row = shared
        skip = None if skip_layer is None else (skip_layer, None)
        return fused_mlp(x, weights, biases, activation, skip=skip, time_row=row, **kwargs)
    encoded = weights[0].shape[1]
    x, weights[0], biases[0] = fold_parts(weights[0], biases[0], parts)
    skip = None
    if skip_layer is not None:
        whole = weights[skip_layer]
        _, skip_weight, biases[skip_layer] = fold_parts(whole, biases[skip_layer], parts)
        weights[skip_layer], skip = whole[:, encoded:], (skip_layer, skip_weight)
    return fused_mlp(x, weights, biases, activation, skip=skip, **kwargs)


def _points_then_row(parts: list) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(x [N, Ex], row [1, Et])`` where ``parts`` are the points' values in columns [0, Ex) then one
    row without gradient in the next Et: the op's ``time_row`` form; else None."""
    if len(parts) != 2:
        return None
    (x, x_columns), (row, row_columns) = parts
    if not (isinstance(x_columns, slice) and isinstance(row_columns, slice)):
        return None
    ex, et = x.shape[-1], row.shape[-1]
    if x_columns.step not in (None, 1) or row_columns.step not in (None, 1):
        return None
    if x_columns.start not in (None, 0) or x_columns.stop != ex or row_columns.start != ex:
        return None
    if row_columns.stop not in (None, ex + et) or row.shape[0] != 1 or x.shape[0] < 2:
        return None
    if row.requires_grad or row.dtype != x.dtype:
        return None
    return x, row


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
