"""``dynamic.hold_unexplained``: after the handover, the Gaussians whose own past the learned physics does
not retrace are kept where they are; those it retraces (a fast rigid rotation about an off-origin axis
among them) move on."""

import pytest
import torch
from tests.conftest import randomised_model

from tracegs.config import make_config
from tracegs.physics.integrate import DynamicsParams, integrate
from tracegs.physics.so3 import axis_angle_to_quat, quat_multiply, quat_normalize

T_MAX = 0.75
OMEGA = torch.tensor([0.0, 0.0, 3.0])  # rad per unit of time about z
PIVOT = torch.tensor([0.3, -0.2, 0.0])  # the axis passes through it
V = torch.tensor([0.4, -0.2, 0.1])
A, K = 0.1, 12.0  # the oscillation x = x0 + A sin(K t) e_x (a shadow's edge, say)
E_X = torch.tensor([1.0, 0.0, 0.0])


def _rotate_about_pivot(x: torch.Tensor, angle: float) -> torch.Tensor:
    c, s = torch.cos(torch.tensor(angle)), torch.sin(torch.tensor(angle))
    r = torch.stack([torch.stack([c, -s, c * 0]), torch.stack([s, c, c * 0]), torch.tensor([0.0, 0, 1])])
    return (x - PIVOT) @ r.T + PIVOT


def _controlled_model(hold: float, n: int = 30):
    """Three groups of ten Gaussians, each given by f_trd the exact velocity and acceleration of its
    f_defo motion at the query time: a rigid rotation about an axis through PIVOT; a translation with V;
    an oscillation along x, which no constant-acceleration motion follows for long."""
    cfg = make_config("tiny", device="cpu", bf16=False)
    cfg.dynamic.hold_unexplained = hold
    cfg.dynamic.hold_unseen = 0.0
    model = randomised_model(cfg, n=n)
    canonical = model.gaussians["means"].detach().clone()
    group = torch.arange(n) // (n // 3)

    def deform(t):
        t = float(t)
        rotated = _rotate_about_pivot(canonical, float(OMEGA[2]) * t)
        means = torch.where((group == 0)[:, None], rotated, canonical + t * V)
        oscillating = canonical + A * torch.sin(torch.tensor(K * t)) * E_X
        means = torch.where((group == 2)[:, None], oscillating, means)
        turn = axis_angle_to_quat((t * OMEGA).expand(n, 3))
        quats = torch.where((group == 0)[:, None], quat_multiply(turn, model.gaussians["quats"]), model.gaussians["quats"])
        return {"means": means, "quats": quats, "scales": model.gaussians["scales"]}

    def query_dynamics(means, t):
        zero = torch.zeros_like(means)
        rigid = (group == 0)[:, None]
        wave = (group == 2)[:, None]
        w = torch.where(rigid, OMEGA, zero)
        v = torch.where(rigid, -torch.linalg.cross(OMEGA, PIVOT), V.expand_as(means))
        v = torch.where(wave, A * K * torch.cos(torch.tensor(K * t)) * E_X, v)
        a = torch.where(wave, -A * K * K * torch.sin(torch.tensor(K * t)) * E_X, zero)
        return DynamicsParams(v, w, a, zero)

    model.deform, model.query_dynamics = deform, query_dynamics
    return model, group


@pytest.mark.parametrize("hold", [1.0, 0.0])
def test_only_gaussians_whose_past_the_physics_misses_are_held(hold):
    model, group = _controlled_model(hold)
    t0, t = model.handover_time(T_MAX), 1.1
    start = model.deform(t0)
    with torch.no_grad():
        means = model.state_at(t, T_MAX)["means"]
        params = model.query_dynamics(start["means"], t0)
        carried = integrate(start["means"], quat_normalize(start["quats"]), params, t - t0, model.dt_max)[0]
    held = (group == 2) if hold > 0 else torch.zeros_like(group, dtype=torch.bool)
    torch.testing.assert_close(means[~held], carried[~held], rtol=0, atol=1e-6)
    torch.testing.assert_close(means[held], start["means"][held], rtol=0, atol=0)
    # the rigid rotation is carried along its circle, far from where it was at the handover
    rotation = (group == 0) & ~held
    expected = _rotate_about_pivot(start["means"][rotation], float(OMEGA[2]) * (t - t0))
    torch.testing.assert_close(means[rotation], expected, rtol=0, atol=2e-2)  # RK2 over 11 steps
    assert float((means[rotation] - start["means"][rotation]).norm(dim=-1).mean()) > 0.3


def test_a_miss_within_the_tolerance_moves_on():
    """The oscillation misses its past by about twice its displacement over the window (plus the floor):
    a tolerance of 3 lets it move on."""
    model, group = _controlled_model(3.0)
    t0 = model.handover_time(T_MAX)
    with torch.no_grad():
        means = model.state_at(1.0, T_MAX)["means"]
        start = model.deform(t0)
        params = model.query_dynamics(start["means"], t0)
        carried = integrate(start["means"], quat_normalize(start["quats"]), params, 1.0 - t0, model.dt_max)[0]
    torch.testing.assert_close(means, carried, rtol=0, atol=1e-6)
