"""The training step's fields as one autograd node (``models/fields_step.py``) against the general path
(the fused MLPs, encodings, deformation and RK2 each their own node): the same Gaussians, losses and
gradients, to the bit."""

import pytest
import torch
from tests.conftest import randomised_model

from tracegs.config import make_config
from tracegs.models import fields_step, fused_mlp


def _model(rows: bool, bf16: bool = False, frame: bool = False, **settings):
    cfg = make_config("tiny", **{"stage2.acceleration_consistency": 0.5, **settings})
    cfg.bf16 = bf16
    model = randomised_model(cfg, n=300)
    if frame:  # (the fields see (x - centre) / scale, ``TraceModel.set_field_frame``)
        model.set_field_frame(torch.tensor([0.3, -0.2, 0.1]), 1.7)
    if rows:
        model.set_static_mask(torch.rand(300, generator=torch.Generator().manual_seed(1)) < 0.4)
    return model


def _step(model, node: bool, t_check=None):
    """The Gaussians and losses of one step, and every parameter's gradient of a random functional."""
    fields_step.ENABLED = node
    try:
        state, losses = model.training_state(0.25, 0.4, t_check=t_check)
    finally:
        fields_step.ENABLED = True
    g = torch.Generator().manual_seed(2)
    total = sum(3.0 * v for v in losses.values())
    for name in ("means", "quats", "scales"):
        total = total + (state[name] * torch.randn(state[name].shape, generator=g)).sum()
    params = [p for p in model.parameters() if p.requires_grad]
    grads = torch.autograd.grad(total, params, allow_unused=True)
    values = {k: v.detach() for k, v in state.items()} | {k: v.detach() for k, v in losses.items()}
    return values, grads


needs_node = pytest.mark.skipif(
    not fields_step.applies(_model(rows=False), 0.25, 0.4), reason="the native field ops are not built here"
)


@needs_node
@pytest.mark.parametrize("frame", [False, True], ids=["world frame", "own frame"])
@pytest.mark.parametrize("rows", [False, True], ids=["all moving", "static rows"])
@pytest.mark.parametrize("t_check", [None, 0.1], ids=["check at t", "check at t_check"])
@pytest.mark.parametrize(
    "settings",
    [
        {},
        {"dynamics.acceleration_depth": 0},
        {"dynamics.angular_accelerations_from_head": False, "dynamics.detach_acceleration_features": False},
        {"stage2.acceleration_consistency": 0.0},
        {"stage2.physics_derivation": False},
        {"dynamics.activation": "relu", "deformation.skip_layer": None},
    ],
    ids=["cpu-fast", "shared head", "own rates, no stop", "no consistency", "no derivation", "relu, no skip"],
)
def test_one_node_is_the_general_path_to_the_bit(frame, rows, t_check, settings):
    model = _model(rows, frame=frame, **settings)
    assert fields_step.applies(model, 0.25, 0.4)
    got, got_grads = _step(model, node=True, t_check=t_check)
    want, want_grads = _step(model, node=False, t_check=t_check)
    assert got.keys() == want.keys()
    for key in want:
        torch.testing.assert_close(got[key], want[key], rtol=0, atol=0)
    assert any(g is not None and g.abs().sum() > 0 for g in want_grads)
    for g, w in zip(got_grads, want_grads, strict=True):
        assert (g is None) == (w is None) or (w is None and not g.any())
        if w is not None:
            torch.testing.assert_close(g, w, rtol=0, atol=0)


@pytest.mark.skipif(not fused_mlp.bf16_products(), reason="no bf16 products in this build")
@needs_node
def test_one_node_in_bf16_is_the_general_path_to_the_bit():
    model = _model(rows=True, bf16=True, frame=True)
    got, got_grads = _step(model, node=True)
    want, want_grads = _step(model, node=False)
    for key in want:
        torch.testing.assert_close(got[key], want[key], rtol=0, atol=0)
    for g, w in zip(got_grads, want_grads, strict=True):
        if w is not None:
            torch.testing.assert_close(g, w, rtol=0, atol=0)


@pytest.mark.parametrize(
    "settings",
    [
        {"dynamics.order": 3},
        {"dynamics.time_frequencies": None},
        {"deformation.kind": "hexplane"},
        {"deformation.detach_input": False},
        {"stage2.integrator": "euler"},
        {"method": "defgs"},
    ],
)
def test_other_configurations_take_the_general_path(settings):
    model = _model(rows=False, **settings)
    assert not fields_step.applies(model, 0.25, 0.4)
    model.training_state(0.25, 0.4)  # (and still train)


def test_no_node_without_gradients_or_a_time_step():
    model = _model(rows=False)
    with torch.no_grad():
        assert not fields_step.applies(model, 0.25, 0.4)
    assert not fields_step.applies(model, 0.25, 0.25)
