"""``dynamic.hold_isolated``: after the handover, moving Gaussians whose neighbourhood stands still (they
draw a shadow across a still surface) are kept where they are; a body's Gaussians move on."""

import pytest
import torch
from tests.conftest import randomised_model

from tracegs.config import make_config
from tracegs.physics.integrate import DynamicsParams

T_MAX = 0.75
V = torch.tensor([0.4, -0.2, 0.1])


def _scene():
    """A still plane of 15 x 15 Gaussians at z = 0; a body of 40 Gaussians in a ball of radius 0.05
    above it; 5 painters in the plane, far apart. Body and painters move with V (f_defo and f_trd)."""
    g = torch.linspace(-1, 1, 15)
    plane = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    plane = torch.cat([plane, torch.zeros(len(plane), 1)], 1)
    body = torch.tensor([0.0, 0.0, 0.5]) + 0.05 * torch.nn.functional.normalize(torch.randn(40, 3), dim=1)
    painters = torch.tensor([[-0.8, -0.8, 0], [0.8, -0.8, 0], [0.8, 0.8, 0], [-0.8, 0.8, 0], [0.35, -0.35, 0]])
    points = torch.cat([plane, body, painters])
    kind = torch.cat([torch.zeros(len(plane)), torch.ones(40), 2 * torch.ones(5)]).long()
    return points, kind


def _controlled_model(hold: float):
    torch.manual_seed(0)
    points, kind = _scene()
    cfg = make_config("tiny", device="cpu", bf16=False)
    cfg.dynamic.hold_isolated = hold
    cfg.dynamic.hold_unseen = 0.0
    model = randomised_model(cfg, n=len(points))
    with torch.no_grad():
        model.gaussians["means"].copy_(points)  # the canonical state is t = 0
    model.freeze_threshold = 0.01  # the plane never moves: frozen
    velocity = torch.where((kind > 0)[:, None], V, torch.zeros(3))

    def deform(t):
        g = model.gaussians
        return {"means": points + float(t) * velocity, "quats": g["quats"], "scales": g["scales"]}

    def query_dynamics(means, t):
        zero = torch.zeros_like(means)
        return DynamicsParams(velocity.clone(), zero, zero, zero)

    model.deform, model.query_dynamics = deform, query_dynamics
    return model, kind


@pytest.mark.parametrize("hold", [0.75, 0.0])
def test_moving_gaussians_amid_still_ones_are_held(hold):
    model, kind = _controlled_model(hold)
    t0, t = model.handover_time(T_MAX), 1.2
    start = model.deform(t0)["means"]
    with torch.no_grad():
        means = model.state_at(t, T_MAX)["means"]
    carried = start + (t - t0) * V
    still = (kind == 0) | ((kind == 2) if hold > 0 else torch.zeros_like(kind, dtype=torch.bool))
    torch.testing.assert_close(means[still], start[still], rtol=0, atol=0)
    torch.testing.assert_close(means[~still], carried[~still], rtol=0, atol=1e-6)


def test_all_moving_is_never_isolated():
    """Without still Gaussians (no freeze), nobody is held, however the Gaussians lie."""
    model, kind = _controlled_model(0.5)
    model.freeze_threshold = 0.0
    t0 = model.handover_time(T_MAX)
    with torch.no_grad():
        means = model.state_at(1.0, T_MAX)["means"]
    start = model.deform(t0)["means"]
    expected = start + (1.0 - t0) * torch.where((kind > 0)[:, None], V, torch.zeros(3))
    torch.testing.assert_close(means, expected, rtol=0, atol=1e-6)
