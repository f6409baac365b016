"""A TRACE training step's fields as one autograd node on the CPU.

``TraceModel.training_state`` (f_defo at t', f_trd at the deformed positions, the RK2 from t' to t,
f_trd again for the acceleration consistency) runs a dozen native ops (the fused MLPs, the
encodings, the deformation applied, the RK2), each with its own autograd node and ~40 ATen ops
between them: at the demo's sizes that glue (Python, autograd's nodes and saved tensors, the
gathers and copies) took about a third of the fields' time. Here the same native ops run in
sequence in one ``torch.autograd.Function``, and its backward calls their backward ops in reverse:
the same operations in the same order, hence the same values and gradients to the bit
(tests/models/test_fields_step.py).

It serves the configuration it was written for, and ``applies`` says where: a CPU, float32, the
Deformable-3DGS MLP (inputs detached) with a second-order equivalent f_trd whose time has its own
frequencies, the midpoint RK2, and the native ops built; the fields in the world's frame or their
own (``TraceModel.set_field_frame``: then ``integrate.params_in_world``'s conversion and its
gradient, as autograd computes them). Elsewhere
(and with ``ENABLED = False``) ``training_state`` runs the general path.

N: Gaussians, M: the moving rows.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..physics import fused
from ..physics.integrate import DynamicsParams, integrate_states, num_substeps, params_in_world
from . import deformation, encoding, fused_mlp
from .deformation import HEAD_COLUMNS, DeformationField
from .encoding import positional_encoding, time_rows

ORDER_TWO = ("velocity", "angular_velocity", "acceleration", "angular_acceleration")
"""f_trd's outputs of a second-order equivalent field, in ``DynamicsParams``' order."""

ENABLED = True
"""Take the one node where it applies (False: the general path, to compare)."""


@dataclass
class _Chain:
    """One fused MLP call's settings (``fused_mlp.fused_mlp``'s) and the names of its output groups."""

    names: list[str]
    groups: list[int]  # the columns of each named output
    layers: int  # how many (weight, bias) pairs of the node's inputs it takes
    activation: int
    skip_layer: int = -1
    stop_from: int = -1
    scaled_from: int = -1
    scale: float = 1.0


def applies(model, t_prime: float, t: float) -> bool:
    """Whether ``training_state`` can take the one node for this step of ``model`` (a ``TraceModel``)."""
    stage = model.stage2
    if not ENABLED or not torch.is_grad_enabled() or model.dynamics is None:
        return False
    if not isinstance(model.deformation, DeformationField) or not model.deformation.cfg.detach_input:
        return False
    dyn = model.dynamics.cfg
    if dyn.order != 2 or not dyn.equivalent or dyn.time_frequencies is None:
        return False
    if stage.integrator != "rk2" or float(t) == float(t_prime):
        return False
    if num_substeps(float(t) - float(t_prime), model.dt_max) > fused.MAX_STEPS:
        return False
    means = model.gaussians["means"]
    if means.device.type != "cpu" or any(
        model.gaussians[k].dtype != torch.float32 for k in ("means", "quats", "scales")
    ):
        return False
    if not (
        encoding.NATIVE
        and deformation.NATIVE_DEFORM
        and fused.ENABLED
        and fused_mlp.serves(model.fields_bf16)
    ):
        return False
    if fused.EXTENSION.load() is None:
        return False
    rows = model.moving_rows
    return (means.shape[0] if rows is None else rows.numel()) >= 2  # (the fused MLP's smallest input)


def training_state(model, t_prime: float, t: float, t_check: float | None):
    """``TraceModel.training_state`` for a step where ``applies``: the Gaussians at ``t`` and the
    weighted auxiliary losses, by one autograd node."""
    stage, dyn = model.stage2, model.dynamics
    g, rows = model.gaussians, model.moving_rows
    defo = model.deformation
    head = defo.heads
    defo_layers = [*defo.layers, head.translation, head.rotation, head.log_scale]
    skip = -1 if defo.cfg.skip_layer is None else defo.cfg.skip_layer + 1
    relu = fused_mlp.ACTIVATION_CODES["relu"]
    chains = [_Chain(["dx", "dq", "dlog_s"], list(HEAD_COLUMNS), len(defo_layers), relu, skip)]
    act, scale = fused_mlp.ACTIVATION_CODES[dyn.cfg.activation], float(dyn.cfg.acceleration_scale)
    layers = list(defo_layers)
    for linears, names, stop_from, scaled_from in dyn.fused_chains():  # (f_trd's, as ``outputs`` calls them)
        stop, scaled = -1 if stop_from is None else stop_from, -1 if scaled_from is None else scaled_from
        chains.append(_Chain(list(names), [3] * len(names), len(linears), act, -1, stop, scaled, scale))
        layers += linears
    moving = g["means"].shape[0] if rows is None else rows.numel()
    t_check = t if t_check is None else t_check
    consistency = stage.acceleration_consistency > 0 and stage.physics_derivation and t_check != t_prime
    share = 1.0 if rows is None else moving / g["means"].shape[0]
    n = num_substeps(t - t_prime, model.dt_max)
    plan = _Plan(
        ops=fused_mlp.EXTENSION.load(),
        rk2=fused.EXTENSION.load(),
        rows=rows,
        chains=chains,
        identity=head.identity,
        frame=None if model.fields_see_world else (model.field_center, float(model.field_scale)),
        to_field=model.to_field_frame,
        bf16=model.fields_bf16,
        t_prime=float(t_prime),
        query_time=float(t_prime if stage.physics_derivation else t),
        t_check=float(t_check),
        t=float(t),
        dt=(float(t) - float(t_prime)) / n,
        steps=n,
        dt_max=model.dt_max,
        frequencies=(
            defo.cfg.position_frequencies,
            defo.cfg.time_frequencies,
            dyn.cfg.num_frequencies,
            dyn.cfg.time_frequencies,
        ),
        consistency=(stage.acceleration_consistency * share) if consistency else None,
    )
    tensors = [layer.weight for layer in layers] + [layer.bias for layer in layers]
    out = _FieldsStep.apply(plan, g["means"], g["quats"], g["scales"], *tensors)
    losses = {"acceleration": out[3]} if consistency else {}
    return {"means": out[0], "quats": out[1], "scales": out[2]}, losses


@dataclass
class _Plan:
    ops: object
    rk2: object
    rows: torch.Tensor | None
    chains: list[_Chain]
    identity: torch.Tensor  # f_defo's rotation head adds it (``DeformationHeads``)
    frame: tuple[torch.Tensor, float] | None  # the fields' frame (centre, scale); None: the world's
    to_field: object  # world positions as the fields see them (``TraceModel.to_field_frame``)
    bf16: bool
    t_prime: float
    query_time: float
    t_check: float
    t: float
    dt: float
    steps: int
    dt_max: float
    frequencies: tuple[int, int, int, int]
    consistency: float | None  # the loss's weight (coefficient times the moving share), or None


def _rows(x: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    return x if rows is None else x.index_select(0, rows)


def _put_rows(x: torch.Tensor, rows: torch.Tensor | None, values: torch.Tensor) -> torch.Tensor:
    return values if rows is None else x.index_copy(0, rows, values)


class _FieldsStep(torch.autograd.Function):
    """Inputs: the plan, the canonical means, quats and log-scales [N, ...], then every chain's
    weights and then every chain's biases (f_defo's layers and its three heads, f_trd's layers and
    head, the own accelerations' layers and head). Outputs: means, quats, log-scales at t [N, ...],
    and the weighted acceleration consistency where the plan has one."""

    @staticmethod
    def forward(ctx, plan: _Plan, means0, quats0, scales0, *tensors):
        ops, rows = plan.ops, plan.rows
        half = len(tensors) // 2
        weights, biases = list(tensors[:half]), list(tensors[half:])
        defo, trd, *own = plan.chains
        # (f_defo's three heads as one last layer, as ``DeformationHeads.stacked``)
        w_defo, b_defo = weights[: defo.layers], biases[: defo.layers]
        w_defo = [*w_defo[:-3], torch.cat(w_defo[-3:])]
        b_defo = [*b_defo[:-3], torch.cat(b_defo[-3:])]
        at = defo.layers
        w_trd, b_trd = weights[at : at + trd.layers], biases[at : at + trd.layers]
        at += trd.layers
        w_own, b_own = (weights[at:], biases[at:]) if own else ([], [])
        lx, lt, ldx, ldt = plan.frequencies

        # f_defo at t' on the moving rows, applied to the canonical Gaussians (``TraceModel.deform``)
        x0 = plan.to_field(_rows(means0, rows))
        defo_in = positional_encoding(x0, lx)
        defo_row = positional_encoding(time_rows(plan.t_prime, x0), lt)
        dx, dq, ds, *defo_saved = _mlp(ops, defo, defo_in, w_defo, b_defo, defo_row, plan.bf16, True)
        dq = dq + plan.identity  # (``DeformationHeads.finish``)
        if plan.frame is not None:
            dx = dx * plan.frame[1]
        means_s, quats_s, scales_s = ops.deform_forward(means0, quats0, scales0, rows, dx, dq, ds)

        # f_trd at (x_t', t'), from the deformed positions without their gradient
        x_run = _rows(means_s, rows).contiguous()
        trd_in = positional_encoding(plan.to_field(x_run), ldx)
        trd_row = positional_encoding(time_rows(plan.query_time, x_run), ldt)
        out = _mlp(ops, trd, trd_in, w_trd, b_trd, trd_row, plan.bf16, True)
        named = dict(zip(trd.names, out, strict=False))
        trd_saved = out[len(trd.names) :]
        own_saved = []
        if own:
            out = _mlp(ops, own[0], trd_in, w_own, b_own, trd_row, plan.bf16, True)
            named |= dict(zip(own[0].names, out, strict=False))
            own_saved = out[len(own[0].names) :]
        params = DynamicsParams(*[named[name] for name in ORDER_TWO])  # (``applies``: second order)
        if plan.frame is not None:
            params = params_in_world(params, *plan.frame)
        v, w, a, e = params[:4]

        # the RK2 from t' to t of the moving rows (``fused.fused_rk2_rows``, straight through)
        x_rows, q_rows = x_run, _rows(quats_s, rows).contiguous()
        motion = [t.contiguous() for t in (v, w, a, e)]
        x_end, q_end = plan.rk2.rk2_forward(x_rows, q_rows, *motion, plan.dt, plan.steps, True)
        # (into the deformed state's own tensors: nothing else reads them)
        means_t = x_end if rows is None else means_s.index_copy_(0, rows, x_end)
        quats_t = q_end if rows is None else quats_s.index_copy_(0, rows, q_end)

        ctx.plan = plan
        ctx.kept = (w_defo, w_trd, w_own, defo_saved, trd_saved, own_saved, defo_row, trd_row)
        ctx.motion = (x_rows, q_rows, *motion)
        ctx.deform = (quats0, dq)
        ctx.signs = None
        if plan.consistency is None:
            return means_t, quats_t, scales_s
        # f_trd's velocities again at t_check where x_t' is carried there, held fixed
        s = plan.t_check - plan.t_prime
        if plan.t_check == plan.t:
            x_check = x_end
        else:
            x_check = integrate_states(x_run, None, params, s, plan.dt_max, "rk2")[0]
        check_in = positional_encoding(plan.to_field(x_check), ldx)
        check_row = positional_encoding(time_rows(plan.t_check, x_check), ldt)
        later = _mlp(ops, trd, check_in, w_trd, b_trd, check_row, plan.bf16, False)
        later = dict(zip(trd.names, later[: len(trd.names)], strict=True))
        later = DynamicsParams(later["velocity"], later["angular_velocity"], None, None)
        if plan.frame is not None:
            later = params_in_world(later, *plan.frame)
        # ``fused.second_order_consistency``'s operations
        gap, ctx.signs = fused.consistency_gap(a, e, v, w, later.velocity, later.angular_velocity, s)
        return means_t, quats_t, scales_s, plan.consistency * gap

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_means, g_quats, g_scales, g_loss=None):
        plan = ctx.plan
        ops, rows = plan.ops, plan.rows
        defo, trd, *own = plan.chains
        w_defo, w_trd, w_own, defo_saved, trd_saved, own_saved, defo_row, trd_row = ctx.kept
        x_rows, q_rows, *motion = ctx.motion

        # the RK2's backward; the moved positions' gradient passes to x_t' unchanged (straight through)
        g_rows = (_rows(g_means, rows).contiguous(), _rows(g_quats, rows).contiguous())
        _, gq0, gv, gw, ga, ge = plan.rk2.rk2_backward(
            *g_rows, x_rows, q_rows, *motion, plan.dt, plan.steps, True
        )
        if ctx.signs is not None and g_loss is not None:
            da, de = fused.consistency_grads(
                ctx.signs, g_loss * plan.consistency, plan.t_check - plan.t_prime
            )
            ga, ge = ga + da, ge + de
        if plan.frame is not None:  # ``params_in_world``'s backward, as autograd's: scale, then the cross
            centre, scale = plan.frame
            centre = centre.to(gw).expand_as(gw)
            gw = gw + torch.linalg.cross(centre, -gv, dim=-1)
            ge = ge + torch.linalg.cross(centre, -ga, dim=-1)
            gv, ga = gv * scale, ga * scale
        named = {"velocity": gv, "angular_velocity": gw, "acceleration": ga, "angular_acceleration": ge}

        d_trd = _mlp_backward(ops, trd, [named[n] for n in trd.names], trd_saved, w_trd, trd_row, plan.bf16)
        d_own = (
            _mlp_backward(ops, own[0], [named[n] for n in own[0].names], own_saved, w_own, trd_row, plan.bf16)
            if own
            else ([], [])
        )
        # f_defo's: the rows' quaternions from the RK2, the positions and scales unchanged
        g_quats_s = _put_rows(g_quats, rows, gq0)
        quats0, dq = ctx.deform
        gq_canonical, gdx, gdq, gds = ops.deform_backward(g_quats_s, g_means, g_scales, quats0, rows, dq)
        if plan.frame is not None:
            gdx = gdx * plan.frame[1]
        d_defo = _mlp_backward(ops, defo, [gdx, gdq, gds], defo_saved, w_defo, defo_row, plan.bf16)
        # the three heads' rows of the stacked last layer
        heads_w, heads_b = d_defo[0][-1].split(HEAD_COLUMNS), d_defo[1][-1].split(HEAD_COLUMNS)
        grads_w = [*d_defo[0][:-1], *heads_w, *d_trd[0], *d_own[0]]
        grads_b = [*d_defo[1][:-1], *heads_b, *d_trd[1], *d_own[1]]
        return None, g_means, gq_canonical, g_scales, *grads_w, *grads_b


def _mlp(ops, chain: _Chain, x, weights, biases, time_row, bf16: bool, save: bool):
    """``fused_mlp``'s op: the chain's output groups, then (``save``) what its backward reads."""
    return ops.mlp_forward(
        x, weights, biases, None, chain.skip_layer, chain.activation, False, bf16, time_row,
        weights[0].shape[1], chain.groups, chain.scaled_from, chain.scale, save,
    )  # fmt: skip


def _mlp_backward(ops, chain: _Chain, grads_out, saved, weights, time_row, bf16: bool):
    """``fused_mlp``'s backward op: (the layers' weight gradients, their bias gradients)."""
    grads = ops.mlp_backward(
        grads_out, saved, weights, None, chain.skip_layer, chain.activation, False, chain.stop_from,
        False, bf16, time_row, weights[0].shape[1], chain.scaled_from, chain.scale,
    )  # fmt: skip
    n = len(weights)
    return grads[:n], grads[n : 2 * n]
