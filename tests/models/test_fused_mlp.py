"""The fused field MLPs (models/fused_mlp.py) against the PyTorch layers they replace, and their own
gradients against finite differences."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest
import torch

from tracegs.config import make_config
from tracegs.models import fused_mlp
from tracegs.models.deformation import DeformationConfig, DeformationField
from tracegs.models.dynamics import DynamicsConfig, DynamicsField

pytestmark = pytest.mark.skipif(fused_mlp.EXTENSION.load() is None, reason="the fused MLP did not build here")


@pytest.fixture(autouse=True)
def any_build(monkeypatch):
    """The fields take the op whatever vectors this build has (they do by themselves with AVX2 or
    AVX-512), so that these tests hold it to the PyTorch layers on every host."""
    monkeypatch.setattr(fused_mlp, "MIN_VECTOR_BYTES", 0)


def randomised(module: torch.nn.Module, dtype=torch.float32, seed: int = 0) -> torch.nn.Module:
    """``module`` with every parameter random (the fields start with zero heads, which would hide
    errors in the layers behind them)."""
    g = torch.Generator().manual_seed(seed)
    module = module.to(dtype)
    with torch.no_grad():
        for p in module.parameters():
            p.copy_(0.3 * torch.randn(p.shape, generator=g, dtype=dtype))
    return module


def outputs_and_grads(field, x: torch.Tensor, t, fused: bool, **kwargs) -> list[torch.Tensor]:
    """The field's outputs at (x, t) and the gradients of a fixed random functional of them with
    respect to its parameters and to x."""
    x = x.clone().requires_grad_()
    previous, fused_mlp.ENABLED = fused_mlp.ENABLED, fused
    try:
        out = field(x, t, **kwargs)
    finally:
        fused_mlp.ENABLED = previous
    out = [o for o in out if o is not None]
    g = torch.Generator().manual_seed(1)
    total = sum((o * torch.randn(o.shape, generator=g, dtype=o.dtype)).sum() for o in out)
    params = [p for p in field.parameters() if p.requires_grad]
    grads = torch.autograd.grad(total, [*params, x], allow_unused=True)
    return out + [torch.zeros_like(p) if d is None else d for p, d in zip([*params, x], grads, strict=True)]


def assert_match(field, x, t, tolerance, **kwargs):
    """Every output and gradient within ``tolerance`` times the largest magnitude of its tensor (a
    gradient sums thousands of points: single elements may cancel to near zero)."""
    ours = outputs_and_grads(field, x, t, True, **kwargs)
    reference = outputs_and_grads(field, x, t, False, **kwargs)
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=tolerance * float(b.detach().abs().max()))


def times(n: int, dtype) -> list:
    """One time for every point (folded into the first layers' bias) and one time per point."""
    return [0.37, torch.linspace(0.0, 1.0, n, dtype=dtype)[:, None]]


@pytest.mark.parametrize(
    "cfg",
    [
        make_config("cpu-fast").deformation,
        DeformationConfig(depth=3, width=40, skip_layer=0, detach_input=False),
        DeformationConfig(depth=2, width=24, skip_layer=None),
    ],
    ids=["cpu-fast", "skip-first", "no-skip"],
)
def test_fused_deformation_field_matches_its_layers(cfg):
    field = randomised(DeformationField(cfg), torch.float64)
    x = torch.randn(37, 3, dtype=torch.float64)
    for t in times(37, torch.float64):
        assert_match(field, x, t, 1e-12)


@pytest.mark.parametrize(
    "cfg",
    [
        make_config("cpu-fast").dynamics,
        DynamicsConfig(depth=3, width=20, num_frequencies=2, activation="relu"),
        DynamicsConfig(depth=2, width=24, num_frequencies=2, order=3, acceleration_depth=2),
    ],
    ids=["cpu-fast", "relu", "order-3-own-rates"],
)
@pytest.mark.parametrize("rates", [True, False])
def test_fused_dynamics_field_matches_its_layers(cfg, rates):
    field = randomised(DynamicsField(cfg), torch.float64)
    x = torch.randn(29, 3, dtype=torch.float64)
    for t in times(29, torch.float64):
        assert_match(field, x, t, 1e-12, rates=rates)


@pytest.mark.parametrize("seed", range(3))
def test_fused_fields_in_float32_agree_to_rounding(seed):
    """In float32 at the demo's sizes: f_trd (SiLU: smooth) in values and gradients, f_defo (ReLU) in
    values. A ReLU's gradient jumps where its input crosses zero, and among 3000 points x 64 units
    some sit within float32 rounding of zero, where the two sums' rounding picks either side (f_defo's
    gradients are held to the layers in float64 above)."""
    cfg = make_config("cpu-fast")
    x = torch.randn(3000, 3, generator=torch.Generator().manual_seed(seed))
    deformation = randomised(DeformationField(cfg.deformation), seed=seed)
    ours, reference = (
        [o.detach() for o in outputs_and_grads(deformation, x, 0.4, fused)[:3]] for fused in (True, False)
    )
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5 * float(b.abs().max()))
    assert_match(randomised(DynamicsField(cfg.dynamics), seed=seed), x, 0.4, 1e-5)


@pytest.mark.parametrize("activation", ["relu", "silu"])
@pytest.mark.parametrize("last_activation", [True, False])
def test_fused_mlp_gradients_match_finite_differences(activation, last_activation):
    g = torch.Generator().manual_seed(0)
    widths = [7, 9, 18, 5]  # not multiples of the kernel's padding

    def param(*shape):
        return torch.randn(*shape, generator=g, dtype=torch.float64).requires_grad_()

    weights = [param(o, i) for i, o in zip(widths[:-1], widths[1:], strict=True)]
    biases = [param(o) for o in widths[1:]]
    x = param(6, widths[0])
    for skip_layer in (1, 0):  # (0: the first layer takes x twice)
        skip = param(widths[skip_layer + 1], widths[0])

        def f(x, skip, *layers, skip_layer=skip_layer):
            return fused_mlp.fused_mlp(
                x, list(layers[:3]), list(layers[3:]), activation, last_activation, skip=(skip_layer, skip)
            )

        assert torch.autograd.gradcheck(f, (x, skip, *weights, *biases))


def test_stopped_outputs_train_the_weights_but_not_the_input():
    g = torch.Generator().manual_seed(0)
    weights = [
        torch.randn(8, 4, generator=g, dtype=torch.float64),
        torch.randn(6, 8, generator=g, dtype=torch.float64),
    ]
    biases = [torch.randn(8, dtype=torch.float64), torch.randn(6, dtype=torch.float64)]
    for p in (*weights, *biases):
        p.requires_grad_()
    x = torch.randn(5, 4, dtype=torch.float64, requires_grad=True)
    out = fused_mlp.fused_mlp(x, weights, biases, "silu", stop_from=2)
    out[:, 2:].sum().backward()
    assert float(x.grad.abs().max()) == 0.0 and float(weights[0].grad.abs().max()) == 0.0
    assert float(weights[1].grad[2:].abs().max()) > 0 and float(weights[1].grad[:2].abs().max()) == 0.0


def test_time_row_and_scaled_output_groups_match_their_layers_and_finite_differences():
    """The first and the skip layer on [x, a row shared by every point] with their whole weights (the
    row's product folded into the biases), and the output in groups with the last columns as
    r |r| / scale: equal to the PyTorch layers on the concatenation, gradients to finite differences."""
    g = torch.Generator().manual_seed(0)

    def param(*shape):
        return (0.5 * torch.randn(*shape, generator=g, dtype=torch.float64)).requires_grad_()

    ex, et, n = 5, 3, 7
    weights = [param(9, ex + et), param(6, ex + et + 9), param(5, 6)]  # (layer 1: [encoding, h])
    biases = [param(9), param(6), param(5)]
    x, row = param(n, ex), torch.randn(1, et, generator=g, dtype=torch.float64)

    def fused(x, *layers):
        return fused_mlp.fused_mlp(
            x, list(layers[:3]), list(layers[3:]), "silu", skip=(1, None), time_row=row,
            groups=(2, 3), scaled_from=2, scale=1.7,
        )  # fmt: skip

    def layers(x, *layers):
        w, b = layers[:3], layers[3:]
        encoded = torch.cat([x, row.expand(n, et)], dim=1)
        h = torch.nn.functional.silu(encoded @ w[0].T + b[0])
        h = torch.nn.functional.silu(torch.cat([encoded, h], dim=1) @ w[1].T + b[1])
        out = h @ w[2].T + b[2]
        return out[:, :2], out[:, 2:] * out[:, 2:].abs() / 1.7

    inputs = (x, *weights, *biases)
    ours, reference = fused(*inputs), layers(*inputs)
    assert [tuple(o.shape) for o in ours] == [(n, 2), (n, 3)]
    probe = [torch.randn(o.shape, generator=g, dtype=torch.float64) for o in reference]
    for a, b in zip(
        [*ours, *torch.autograd.grad(ours, inputs, probe)],
        [*reference, *torch.autograd.grad(reference, inputs, probe)],
        strict=True,
    ):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)
    assert torch.autograd.gradcheck(fused, inputs)


def test_without_a_gradient_to_come_the_op_keeps_no_activations():
    """f_trd's second query runs under no_grad: the op then keeps only its output (and gives the same
    values as when it keeps every layer's z or h for a backward)."""
    g = torch.Generator().manual_seed(0)
    weights = [torch.randn(64, 39, generator=g) * 0.2, torch.randn(9, 64, generator=g) * 0.2]
    biases = [torch.randn(64, generator=g), torch.randn(9, generator=g)]
    x = torch.randn(300, 39, generator=g)
    ops = fused_mlp.EXTENSION.load()
    silu, linear_last, bf16, time_row, scaled_from, scale = 1, False, False, None, -1, 1.0
    args = (x, weights, biases, None, -1, silu, linear_last, bf16, time_row, 0, [9], scaled_from, scale)
    kept, nothing = ops.mlp_forward(*args, True), ops.mlp_forward(*args, False)
    assert len(kept) == 1 + 1 + 2 and len(nothing) == 1 + 1  # [output, x, each layer's z or h] / [output, x]
    assert torch.equal(kept[0], nothing[0])
    for p in (*weights, *biases):
        p.requires_grad_()
    with torch.no_grad():
        quiet = fused_mlp.fused_mlp(x, weights, biases, "silu")
    assert torch.equal(quiet, fused_mlp.fused_mlp(x, weights, biases, "silu").detach())


def test_where_the_fused_path_applies():
    x = torch.randn(10, 3)
    assert fused_mlp.applies(x)
    assert not fused_mlp.applies(x[:1])  # a single point: every part folds into the bias
    with torch.autocast("cpu", dtype=torch.bfloat16):  # bf16: this op's bf16 products, else oneDNN's
        assert fused_mlp.applies(x) == fused_mlp.bf16_products()
        assert not fused_mlp.applies(x.double())
    previous, fused_mlp.ENABLED = fused_mlp.ENABLED, False
    try:
        assert not fused_mlp.applies(x)
    finally:
        fused_mlp.ENABLED = previous


@pytest.mark.skipif(platform.machine() != "x86_64", reason="x86 instruction sets")
def test_fused_mlp_built_for_avx2_matches_its_layers(tmp_path):
    """The AVX2 build (what most laptops run; 16 vector registers, other register blocks) against the
    PyTorch layers, in a process of its own built with TRACEGS_MARCH (the default build here may be
    AVX-512)."""
    script = (
        "import torch\n"
        "from tracegs.models import fused_mlp\n"
        "from tracegs.models.dynamics import DynamicsConfig, DynamicsField\n"
        "assert fused_mlp.EXTENSION.load().vector_bytes() == 32\n"
        "assert fused_mlp.applies(torch.zeros(2, 3))  # (the fields take it there by themselves)\n"
        "torch.manual_seed(0)\n"
        "field = DynamicsField(DynamicsConfig(depth=3, width=40, num_frequencies=2)).double()\n"
        "with torch.no_grad():\n"
        "    for p in field.parameters():\n"
        "        p.copy_(0.3 * torch.randn_like(p))\n"
        "x = torch.randn(77, 3, dtype=torch.float64)\n"
        "def run(fused):\n"
        "    fused_mlp.ENABLED = fused\n"
        "    out = field(x, 0.3)\n"
        "    total = sum((o * (i + 1)).sum() for i, o in enumerate(out) if o is not None)\n"
        "    return [*[o for o in out if o is not None], *torch.autograd.grad(total, list(field.parameters()))]\n"
        "for a, b in zip(run(True), run(False), strict=True):\n"
        "    torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)\n"
    )
    env = {**os.environ, "TRACEGS_MARCH": "x86-64-v3"}  # (a build of its own in the cache, keyed by -march)
    res = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-2000:]


def _bf16(t: torch.Tensor) -> torch.Tensor:
    return t.to(torch.bfloat16).to(t.dtype)


def _bf16_reference(x, weights, biases, activation, last_activation, skip, grad):
    """The bf16 products' MLP in float64, with explicit backward: every product's operands rounded to
    bf16 (the forward's h and W, the input gradients' dz and W, the weights' gradients' dz and h or x),
    the biases' gradients from the unrounded dz. Returns [output, d weights..., d biases..., d skip
    weight, d x]."""

    def act(z):
        return torch.relu(z) if activation == "relu" else z * torch.sigmoid(z)

    def act_grad(z):
        if activation == "relu":
            return (z > 0).to(z.dtype)
        s = torch.sigmoid(z)
        return s * (1 + z * (1 - s))

    skip_layer, skip_weight = skip
    layers = len(weights)
    hs, zs = [x], []
    for i in range(layers):
        z = _bf16(hs[-1]) @ _bf16(weights[i]).T + biases[i]
        if i == skip_layer:
            z = z + _bf16(x) @ _bf16(skip_weight).T
        zs.append(z)
        hs.append(act(z) if i < layers - 1 or last_activation else z)
    dz = grad * act_grad(zs[-1]) if last_activation else grad
    d_weights, d_biases, d_x = [None] * layers, [None] * layers, torch.zeros_like(x)
    for i in range(layers - 1, -1, -1):
        d_weights[i], d_biases[i] = _bf16(dz).T @ _bf16(hs[i]), dz.sum(0)
        if i == skip_layer:
            d_skip = _bf16(dz).T @ _bf16(x)
            d_x = d_x + _bf16(dz) @ _bf16(skip_weight)
        if i == 0:
            d_x = d_x + _bf16(dz) @ _bf16(weights[0])
            break
        dz = (_bf16(dz) @ _bf16(weights[i])) * act_grad(zs[i - 1])
    return [hs[-1], *d_weights, *d_biases, d_skip, d_x]


@pytest.mark.skipif(not fused_mlp.bf16_products(), reason="no bf16 products on this CPU or build")
@pytest.mark.parametrize(
    "widths, activation, skip_layer, last_activation",
    [
        ([51, 64, 64, 64, 64, 10], "relu", 3, False),
        ([39, 64, 64, 9], "silu", 0, False),
        ([7, 9, 18, 5], "silu", 1, True),
    ],
    ids=["f_defo", "f_trd", "odd-widths"],
)
def test_bf16_products_match_their_float64_emulation(widths, activation, skip_layer, last_activation):
    """Under bf16 autocast the op's outputs and gradients equal the same MLP in float64 with each
    product's operands rounded to bf16 (to float rounding: the float sums, and a rare operand that
    rounds the other way from a float32 rather than a float64 value)."""
    g = torch.Generator().manual_seed(0)

    def param(*shape):
        return (0.3 * torch.randn(*shape, generator=g)).requires_grad_()

    weights = [param(o, i) for i, o in zip(widths[:-1], widths[1:], strict=True)]
    biases = [param(o) for o in widths[1:]]
    skip_weight = param(widths[skip_layer + 1], widths[0])
    x = torch.randn(301, widths[0], generator=g).requires_grad_()  # (rows: not a multiple of any block)
    grad = torch.randn(301, widths[-1], generator=g)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = fused_mlp.fused_mlp(
            x, weights, biases, activation, last_activation, skip=(skip_layer, skip_weight)
        )
    out.backward(grad)
    ours = [out.detach(), *[p.grad for p in (*weights, *biases, skip_weight, x)]]
    as64 = [p.detach().double() for p in weights], [p.detach().double() for p in biases]
    skip = (skip_layer, skip_weight.detach().double())
    reference = _bf16_reference(x.detach().double(), *as64, activation, last_activation, skip, grad.double())
    for a, b in zip(ours, reference, strict=True):
        torch.testing.assert_close(a.double(), b, rtol=0, atol=1e-4 * float(b.abs().max()))
    # and bf16 products are not float32's: the comparison can fail
    with torch.no_grad():
        plain = fused_mlp.fused_mlp(
            x, weights, biases, activation, last_activation, skip=(skip_layer, skip_weight)
        )
    assert float((plain - out.detach()).abs().max()) > 1e-3 * float(plain.abs().max())


@pytest.mark.skipif(not fused_mlp.bf16_products(), reason="no bf16 products on this CPU or build")
def test_bf16_products_with_a_time_row_match_their_float64_emulation():
    """Under bf16 autocast, the first and the skip layer on [x, a time row] (whole weights, outputs by
    groups): the time row's product is folded into the biases in float, not rounded to bf16, so the op
    equals the float64 emulation of the x part's MLP with those biases; the whole weights' gradients
    hold the time columns' as the bias gradient times the row."""
    g = torch.Generator().manual_seed(0)

    def param(*shape):
        return (0.3 * torch.randn(*shape, generator=g)).requires_grad_()

    ex, et, n = 39, 13, 301
    weights = [param(64, ex + et), param(64, 64), param(64, ex + et + 64), param(9, 64)]
    biases = [param(64), param(64), param(64), param(9)]
    x, row = torch.randn(n, ex, generator=g).requires_grad_(), torch.randn(1, et, generator=g)
    grad = torch.randn(n, 9, generator=g)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        outs = fused_mlp.fused_mlp(x, weights, biases, "silu", skip=(2, None), time_row=row, groups=(3, 6))
    torch.cat(outs, dim=1).backward(grad)
    w64 = [w.detach().double() for w in weights]
    t64 = row.double()[0]
    folded = [b.detach().double() for b in biases]
    folded[0] = folded[0] + w64[0][:, ex:] @ t64
    folded[2] = folded[2] + w64[2][:, ex : ex + et] @ t64
    parts = [w64[0][:, :ex], w64[1], w64[2][:, ex + et :], w64[3]]
    skip = (2, w64[2][:, :ex])
    out, *rest = _bf16_reference(x.detach().double(), parts, folded, "silu", False, skip, grad.double())
    d_w, d_b, d_skip, d_x = rest[:4], rest[4:8], rest[8], rest[9]
    time_columns = [torch.outer(d_b[i], t64) for i in (0, 2)]
    reference = [
        out,
        torch.cat([d_w[0], time_columns[0]], dim=1),
        d_w[1],
        torch.cat([d_skip, time_columns[1], d_w[2]], dim=1),
        d_w[3],
        *d_b,
        d_x,
    ]
    ours = [torch.cat(outs, dim=1).detach(), *[p.grad for p in (*weights, *biases, x)]]
    # (d x and the weights' gradients take dz rounded to bf16 after up to three bf16 roundings and two
    # products: a dz that rounds the other way from a float32 rather than a float64 value moves them by
    # up to ~4e-4 of their largest; unrounded operands for the weights' gradients would be off by ~2e-3)
    tolerances = [1e-4] + [5e-4] * 4 + [1e-4] * 4 + [1e-3]
    for a, b, tolerance in zip(ours, reference, tolerances, strict=True):
        torch.testing.assert_close(a.double(), b, rtol=0, atol=tolerance * float(b.abs().max()))


def test_second_derivatives_are_refused_not_wrong():
    w = torch.randn(4, 3, dtype=torch.float64, requires_grad=True)
    b = torch.zeros(4, dtype=torch.float64, requires_grad=True)
    x = torch.randn(5, 3, dtype=torch.float64, requires_grad=True)
    out = fused_mlp.fused_mlp(x, [w], [b], "silu", last_activation=True)
    (grad,) = torch.autograd.grad(out.sum(), x, create_graph=True)
    with pytest.raises(RuntimeError):
        grad.sum().backward()
