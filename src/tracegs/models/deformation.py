"""The auxiliary deformation field f_defo(x0, t) -> (dx, dq, dlog_s) (Section 3.1, Eq. 2, Appendix).

N: Gaussians, W: hidden width, E: encoded input channels.
Two fields behind one interface, ``forward(x0 [N, 3], t) -> (dx [N, 3], dq [N, 4], dlog_s [N, 3])``:
the Deformable-3DGS MLP (TRACE's default) and the 4DGS HexPlane (TRACE_4dgs). Both end in the same
zero-initialised heads, so a new field is exactly "no motion": dx = 0, dq = (1, 0, 0, 0), dlog_s = 0.
Zero heads do not stop training: the heads' own gradients (hidden features x upstream gradient) are
non-zero, and once the first optimiser step has made them non-zero the gradient reaches every layer.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from tracegs.models import fused_mlp
from tracegs.models.encoding import encoding_dim, linear_of_parts, positional_encoding, time_column, time_rows
from tracegs.models.hexplane import HexPlane, HexPlaneConfig
from tracegs.physics.so3 import quat_multiply, quat_normalize

DeformationOutput = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # dx [N, 3], dq [N, 4], dlog_s [N, 3]


@dataclass
class DeformationConfig:
    """The deformation field f_defo (defaults: the paper's Appendix)."""

    kind: str = "mlp"
    """"mlp" (Deformable 3DGS, TRACE) or "hexplane" (4DGS, TRACE_4dgs)."""
    depth: int = 8
    """Hidden layers of the MLP, each followed by a ReLU."""
    width: int = 256
    """Hidden width of the MLP."""
    skip_layer: int | None = 4
    """After this hidden layer (0-based) the encoded input is concatenated again (Deformable 3DGS:
    depth // 2); None for no skip."""
    detach_input: bool = True
    """Feed the canonical centres to the field without gradient, as Deformable 3DGS does: x0 then
    learns through x0 + dx only, and the backward skips the input-gradient pass of the encoding."""
    position_frequencies: int = 8
    """Frequencies of the positional encoding of x0 (TRACE's Appendix: 8; Deformable 3DGS: 10)."""
    time_frequencies: int = 6
    """Frequencies of the encoding of t (Deformable 3DGS on synthetic scenes: 6; Appendix: 5)."""
    hexplane: HexPlaneConfig = field(default_factory=HexPlaneConfig)
    """Grid and decoder of the "hexplane" kind."""


HEAD_COLUMNS = (3, 4, 3)
"""The heads' outputs, stacked in this order: translation, rotation (a quaternion), log-scale."""


class DeformationHeads(nn.Module):
    """Zero-initialised linear heads W -> (dx 3, dq 4, dlog_s 3), the identity quaternion added to dq.

    Outputs are cast to ``dtype`` (the inputs' dtype), so that under bf16 autocast the consumers get
    float32.
    """

    def __init__(self, width: int):
        super().__init__()
        self.translation = nn.Linear(width, 3)
        self.rotation = nn.Linear(width, 4)
        self.log_scale = nn.Linear(width, 3)
        for head in (self.translation, self.rotation, self.log_scale):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        self.register_buffer("identity", torch.tensor([1.0, 0.0, 0.0, 0.0]), persistent=False)

    def forward(self, h: torch.Tensor, dtype: torch.dtype) -> DeformationOutput:
        return self.split(torch.nn.functional.linear(h, *self.stacked()), dtype)

    def stacked(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The three heads as one layer's weight [10, W] and bias [10]: one product instead of three,
        forward and backward (the parameters stay three layers, as checkpoints hold them)."""
        heads = (self.translation, self.rotation, self.log_scale)
        return torch.cat([head.weight for head in heads]), torch.cat([head.bias for head in heads])

    def split(self, out: torch.Tensor, dtype: torch.dtype) -> DeformationOutput:
        """The stacked heads' output [N, 10] as ``(dx, dq, dlog_s)`` in ``dtype``."""
        return self.finish(*out.to(dtype).split(HEAD_COLUMNS, dim=-1), dtype)

    def finish(
        self, dx: torch.Tensor, dq: torch.Tensor, dlog_s: torch.Tensor, dtype: torch.dtype
    ) -> DeformationOutput:
        """The three heads' outputs as ``(dx, dq, dlog_s)`` in ``dtype`` (the rotation's about the
        identity)."""
        return dx.to(dtype), dq.to(dtype) + self.identity.to(dtype), dlog_s.to(dtype)


class DeformationField(nn.Module):
    """Deformable-3DGS MLP: ``(PE(x0), PE(t))`` -> depth x width ReLU MLP with one skip -> heads."""

    def __init__(self, cfg: DeformationConfig):
        super().__init__()
        self.cfg = cfg
        in_dim = encoding_dim(3, cfg.position_frequencies) + encoding_dim(1, cfg.time_frequencies)
        layers = []
        for i in range(cfg.depth):
            fan_in = in_dim if i == 0 else cfg.width
            if cfg.skip_layer is not None and i == cfg.skip_layer + 1:
                fan_in += in_dim
            layers.append(nn.Linear(fan_in, cfg.width))
        self.layers = nn.ModuleList(layers)
        self.heads = DeformationHeads(cfg.width)

    def encode(self, x0: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """``[PE(x0), PE(t)]`` [N, E]."""
        t = time_column(t, x0)
        return torch.cat(
            [
                positional_encoding(x0, self.cfg.position_frequencies),
                positional_encoding(t, self.cfg.time_frequencies),
            ],
            dim=-1,
        )

    def forward(self, x0: torch.Tensor, t: float | torch.Tensor) -> DeformationOutput:
        """``(dx, dq, dlog_s)`` of the Gaussians at canonical positions ``x0`` [N, 3] at time ``t``.

        The same function as the MLP on ``encode(x0, t)`` with the skip's concatenation, evaluated
        part by part (``linear_of_parts``): a time shared by all points enters as a bias.
        """
        ex = encoding_dim(3, self.cfg.position_frequencies)
        e = ex + encoding_dim(1, self.cfg.time_frequencies)
        inputs = [
            (positional_encoding(x0, self.cfg.position_frequencies), slice(0, ex)),
            (positional_encoding(time_rows(t, x0), self.cfg.time_frequencies), slice(ex, e)),
        ]
        skip = None if self.cfg.skip_layer is None else self.cfg.skip_layer + 1
        if fused_mlp.applies(x0):
            return self._fused_forward(inputs, skip, x0.dtype)
        h = torch.relu(linear_of_parts(self.layers[0], inputs))
        for i, layer in enumerate(self.layers[1:], start=1):
            if i == skip:
                h = torch.relu(linear_of_parts(layer, [*inputs, (h, slice(e, None))]))
            else:
                h = torch.relu(layer(h))
        return self.heads(h, x0.dtype)

    def _fused_forward(self, inputs: list, skip: int | None, dtype: torch.dtype) -> DeformationOutput:
        """``forward`` as one native op (``fused_mlp``): the layers, the skip's concatenation as a
        second product of the encoding, and the three heads as the last layer, output by head."""
        head_weight, head_bias = self.heads.stacked()
        weights = [*[layer.weight for layer in self.layers], head_weight]
        biases = [*[layer.bias for layer in self.layers], head_bias]
        dx, dq, dlog_s = fused_mlp.fused_mlp_of_parts(
            inputs, weights, biases, "relu", skip_layer=skip, groups=HEAD_COLUMNS
        )
        return self.heads.finish(dx, dq, dlog_s, dtype)


class HexPlaneDeformationField(nn.Module):
    """4DGS deformation field: HexPlane features [N, S C] -> small ReLU MLP -> the same heads."""

    def __init__(self, cfg: DeformationConfig, aabb: torch.Tensor | None = None):
        super().__init__()
        self.cfg = cfg
        self.grid = HexPlane(cfg.hexplane, aabb)
        width = cfg.hexplane.decoder_width
        self.layers = nn.ModuleList(
            [
                nn.Linear(self.grid.out_dim if i == 0 else width, width)
                for i in range(cfg.hexplane.decoder_depth)
            ]
        )
        self.heads = DeformationHeads(width)

    def forward(self, x0: torch.Tensor, t: float | torch.Tensor) -> DeformationOutput:
        """``(dx, dq, dlog_s)`` of the Gaussians at canonical positions ``x0`` [N, 3] at time ``t``."""
        h = self.grid(x0, time_column(t, x0))
        for layer in self.layers:
            h = torch.relu(layer(h))
        return self.heads(h, x0.dtype)

    def fit_bounds(self, points: torch.Tensor) -> None:
        """Box the grid around the canonical Gaussians ``points`` [N, 3] (see ``HexPlane.fit_bounds``)."""
        self.grid.fit_bounds(points)

    def regularization_losses(self) -> dict[str, torch.Tensor]:
        """The grid's weighted regularisers (plane TV, time smoothness, time L1)."""
        return self.grid.regularization_losses()


def make_deformation_field(cfg: DeformationConfig, aabb: torch.Tensor | None = None) -> nn.Module:
    """The field named by ``cfg.kind``; ``aabb`` [2, 3] (scene bounds) is used by the HexPlane."""
    if cfg.kind == "mlp":
        return DeformationField(cfg)
    if cfg.kind == "hexplane":
        return HexPlaneDeformationField(cfg, aabb)
    raise ValueError(f"unknown deformation field kind {cfg.kind!r}; expected 'mlp' or 'hexplane'")


def apply_deformation(
    x0: torch.Tensor,  # [N, 3] canonical means
    q0: torch.Tensor,  # [N, 4] canonical quaternions (wxyz)
    log_s0: torch.Tensor,  # [N, 3] canonical log-scales
    dx: torch.Tensor,  # [N, 3]
    dq: torch.Tensor,  # [N, 4] unnormalised
    dlog_s: torch.Tensor,  # [N, 3]
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Gaussians at time t (Eq. 2 / Appendix): ``x0 + dx``, ``normalize(dq) o q0``, ``log_s0 + dlog_s``.

    The returned quaternion has the norm of ``q0`` (unit if ``q0`` is); scales stay in log space
    (``s_t = exp(log_s0 + dlog_s) = s0 * exp(dlog_s)``).
    """
    return x0 + dx, quat_multiply(quat_normalize(dq), q0), log_s0 + dlog_s


def deform_rows(
    canonical: list[torch.Tensor],
    rows: torch.Tensor | None,
    dx: torch.Tensor,
    dq: torch.Tensor,
    dlog_s: torch.Tensor,
) -> list[torch.Tensor]:
    """``apply_deformation`` on the rows ``rows`` [M] of the canonical Gaussians ``canonical`` (means
    [N, 3], quats [N, 4], log-scales [N, 3]; every row with None), the other rows kept: the three
    tensors [N, ...]. ``dx``, ``dq``, ``dlog_s``: the field's outputs for those rows [M, ...].

    Float32/64 on the CPU takes one native op forward and one backward (``csrc/mlp_cpu.cpp``, where
    the extension is built); the same values and gradients to rounding (tests/models/test_native_field_ops.py)."""
    ops = _deform_ops(canonical, dx, dq, dlog_s)
    if ops is not None:
        return list(_NativeDeform.apply(*canonical, rows, dx, dq, dlog_s, ops))
    moved = apply_deformation(*(canonical if rows is None else [c[rows] for c in canonical]), dx, dq, dlog_s)
    if rows is None:
        return list(moved)
    return [c.index_copy(0, rows, v) for c, v in zip(canonical, moved, strict=True)]


NATIVE_DEFORM = True
"""``deform_rows`` takes the native op where it applies (False: the PyTorch ops, to compare)."""


def _deform_ops(canonical: list[torch.Tensor], *outputs: torch.Tensor):
    tensors = [*canonical, *outputs]
    dtype = tensors[0].dtype
    if not NATIVE_DEFORM or dtype not in (torch.float32, torch.float64):
        return None
    if any(t.device.type != "cpu" or t.dtype != dtype or t.dim() != 2 for t in tensors):
        return None
    return fused_mlp.EXTENSION.load()


class _NativeDeform(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x0, q0, s0, rows, dx, dq, ds, ops):
        ctx.save_for_backward(q0, rows, dq)
        ctx.ops = ops
        return tuple(ops.deform_forward(x0, q0, s0, rows, dx, dq, ds))

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, gx, gq, gs):
        q0, rows, dq = ctx.saved_tensors
        gq0, gdx, gdq, gds = ctx.ops.deform_backward(gq, gx, gs, q0, rows, dq)
        return gx, gq0, gs, None, gdx, gdq, gds, None
