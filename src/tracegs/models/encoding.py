"""Input encodings shared by the deformation field and the dynamics field.

N: points, D: input channels, L: frequencies.
"""

from __future__ import annotations

import torch

from ..cpp import EXTENSIONS


def encoding_dim(in_dim: int, num_frequencies: int, include_input: bool = True) -> int:
    """Channels of ``positional_encoding`` for ``in_dim`` inputs: ``D (1 + 2L)`` (or ``2 D L``)."""
    return in_dim * (2 * num_frequencies + int(include_input))


NATIVE = True
"""Compute float32 encodings on the CPU with the native op (``csrc/mlp_cpu.cpp``) where it is built;
False: always the ATen ops below (to compare)."""


def positional_encoding(u: torch.Tensor, num_frequencies: int, include_input: bool = True) -> torch.Tensor:
    """``[u, sin(2^0 u), cos(2^0 u), ..., sin(2^(L-1) u), cos(2^(L-1) u)]`` [..., D (1 + 2L)].

    No pi factor (as the authors' and Deformable 3DGS's embedder); the channel order is
    the Deformable 3DGS one (frequency-major, then sin/cos, then input channel). Float32 on the CPU
    takes one native op (``NATIVE``; the same values to ~2e-7), else ATen's.
    """
    ops = _native_ops(u)
    if ops is not None:
        flat = u.reshape(-1, u.shape[-1])
        if u.requires_grad and torch.is_grad_enabled():
            out = _NativeEncoding.apply(flat, num_frequencies, include_input, ops)
        else:  # (the fields' inputs in training: no autograd node to make)
            out = ops.positional_encoding(flat, num_frequencies, include_input)
        return out.reshape(*u.shape[:-1], out.shape[-1])
    parts = [u] if include_input else []
    if num_frequencies > 0:
        freqs = _frequencies(u, num_frequencies)  # [L]
        angles = u[..., None, :] * freqs[:, None]  # [..., L, D]
        sincos = torch.stack([torch.sin(angles), torch.cos(angles)], dim=-2)  # [..., L, 2, D]
        parts.append(sincos.flatten(-3))
    return torch.cat(parts, dim=-1)


def _native_ops(u: torch.Tensor):
    """The native encoding's ops for ``u``, or None where ATen's apply (not float32 on the CPU, no
    channels, ``NATIVE`` off, the extension not built)."""
    if not NATIVE or u.device.type != "cpu" or u.dtype != torch.float32 or u.dim() == 0 or not u.shape[-1]:
        return None
    return EXTENSIONS["tracegs_mlp_cpu"].load()


def _frequencies(like: torch.Tensor, num_frequencies: int) -> torch.Tensor:
    """[L] the encoding's angular frequencies 2^k (exact powers of two), like ``like``."""
    return like.new_tensor([2.0**k for k in range(num_frequencies)])


class _NativeEncoding(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, num_frequencies, include_input, ops):
        out = ops.positional_encoding(u, num_frequencies, include_input)
        if ctx.needs_input_grad[0]:
            ctx.save_for_backward(out)  # (its sines and cosines give the derivative)
        ctx.settings = (num_frequencies, include_input, u.shape[1])
        return out

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_out):
        (out,) = ctx.saved_tensors
        num_frequencies, include_input, d = ctx.settings
        first = d if include_input else 0
        grad = grad_out[:, :d] if include_input else grad_out.new_zeros(out.shape[0], d)
        if num_frequencies:
            sincos = out[:, first:].reshape(-1, num_frequencies, 2, d)
            g = grad_out[:, first:].reshape(-1, num_frequencies, 2, d)
            freqs = _frequencies(out, num_frequencies)[:, None]
            # d sin(a u) = a cos(a u), d cos(a u) = -a sin(a u)
            grad = grad + ((g[:, :, 0] * sincos[:, :, 1] - g[:, :, 1] * sincos[:, :, 0]) * freqs).sum(1)
        return grad, None, None, None


def time_rows(t: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """The time(s) ``t`` as a column with the device and dtype of ``like`` [N, ...]: [1, 1] when one
    time holds for every point (then its encoding is computed once), else [N, 1].

    ``t`` may be a Python number, a 0-d / [1] tensor (one time for all points), or [N] / [N, 1].
    """
    t = torch.as_tensor(t, dtype=like.dtype, device=like.device)
    return t.reshape(1, 1) if t.numel() == 1 else t.reshape(like.shape[0], 1)


def time_column(t: float | torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """``time_rows`` as a full column [N, 1] (one time expanded to every point, without a copy)."""
    return time_rows(t, like).expand(like.shape[0], 1)


def linear_of_parts(
    layer: torch.nn.Linear, parts: list[tuple[torch.Tensor, slice | torch.Tensor]]
) -> torch.Tensor:
    """``layer`` applied to the concatenation of ``parts`` without building it.

    Each part is its values [N, D_k] or [1, D_k] and the columns of ``layer.weight`` they occupy (a
    slice or an index tensor). A part with a single row (the encoded time of a frame, the same for
    every point) is folded into the bias: the fields' inputs are mostly ``[PE(x), PE(t)]`` with one t
    per call, so this saves the [N, E] concatenation and the time's share of the first GEMM (and the
    same again at Deformable 3DGS's skip layer). Equal to ``layer(cat)`` up to float rounding.
    """
    return product_of_parts(layer.weight, layer.bias, parts)


def fold_single_rows(
    weight: torch.Tensor, bias: torch.Tensor | None, parts: list[tuple[torch.Tensor, slice | torch.Tensor]]
) -> tuple[torch.Tensor | None, list[tuple[torch.Tensor, torch.Tensor]]]:
    """The parts of ``product_of_parts`` with a single row folded into the bias (then [1, O]): that
    bias and the other parts as (values, their weight columns)."""
    rows = []
    for values, columns in parts:
        part_weight = weight[:, columns]
        if values.shape[0] == 1:
            bias = torch.nn.functional.linear(values, part_weight, bias)
        else:
            rows.append((values, part_weight))
    return bias, rows


def product_of_parts(
    weight: torch.Tensor, bias: torch.Tensor | None, parts: list[tuple[torch.Tensor, slice | torch.Tensor]]
) -> torch.Tensor:
    """``linear_of_parts`` with the layer given as its ``weight`` [O, E] and ``bias`` [O] (e.g. two
    layers on the same input stacked into one product)."""
    bias, rows = fold_single_rows(weight, bias, parts)
    if not rows:  # a single point: every part was folded, the result is the bias row
        return bias
    (values, part_weight), *rest = rows
    # the bias (with the folded rows) enters the first product (addmm), the other parts add theirs
    out = torch.nn.functional.linear(values, part_weight, None if bias is None else bias.reshape(-1))
    for values, part_weight in rest:
        out = torch.addmm(out, values, part_weight.t())
    return out
