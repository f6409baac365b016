"""``extrapolation.hold_surface``: after the handover, a moving Gaussian amid still ones (it draws something
across a still surface, a shadow) holds still (``surface_painters="hold"``) or is stopped where its path
would leave that surface (``"edge"``; while on it the physics carries it on); a body's Gaussians are
always carried on."""

import pytest
import torch
from tests.conftest import randomised_model

from tracegs.config import make_config
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.physics.integrate import DynamicsParams, num_substeps

T_MAX = 0.75
SPACING = 2 / 14  # the still plane's grid step
UP = torch.tensor([0.0, 0.0, 1.0])


def _scene():
    """A still plane of 15 x 15 Gaussians at z = 0; a body of 40 Gaussians in a ball of radius 0.05 at
    z = 0.5; painter A at (-0.5, -0.5, 0) and painter B at (0.5, 0.5, 0), both in the plane.
    f_defo moves the body up, A and B along the plane; f_trd moves the body and A up (A leaves the
    plane) and B along the plane (B stays on it)."""
    g = torch.linspace(-1, 1, 15)
    plane = torch.stack(torch.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    plane = torch.cat([plane, torch.zeros(len(plane), 1)], 1)
    body = torch.tensor([0.0, 0.0, 0.5]) + 0.05 * torch.nn.functional.normalize(torch.randn(40, 3), dim=1)
    painters = torch.tensor([[-0.5, -0.5, 0.0], [0.5, 0.5, 0.0]])
    points = torch.cat([plane, body, painters])
    n_plane = len(plane)
    defo = torch.zeros_like(points)
    defo[n_plane : n_plane + 40] = UP
    defo[-2:] = torch.tensor([[0.3, 0.0, 0.0], [0.2, 0.1, 0.0]])
    phys = defo.clone()
    phys[-2] = UP
    return points, defo, phys, n_plane


def _controlled_model(fraction: float, painters: str = "edge"):
    """The model of ``_scene`` with ``extrapolation.surface_still_fraction = fraction`` (0: ``hold_surface``
    off) and ``surface_painters = painters``, and its predictor."""
    torch.manual_seed(0)
    points, defo, phys, n_plane = _scene()
    cfg = make_config("tiny", device="cpu", bf16=False)
    cfg.extrapolation.hold_surface = fraction > 0
    if fraction > 0:
        cfg.extrapolation.surface_still_fraction = fraction
    cfg.extrapolation.hold_unseen = False
    cfg.extrapolation.surface_painters = painters
    model = randomised_model(cfg, n=len(points))
    with torch.no_grad():
        model.gaussians["means"].copy_(points)  # the canonical state is t = 0
    state = ExtrapolationState(t_max=T_MAX, freeze_threshold=0.01)  # the plane never moves: frozen

    def deform(t):
        g = model.gaussians
        return {"means": points + float(t) * defo, "quats": g["quats"], "scales": g["scales"]}

    def query_dynamics(means, t):
        zero = torch.zeros_like(means)
        return DynamicsParams(phys.clone(), zero, zero, zero)

    model.deform, model.query_dynamics = deform, query_dynamics
    return model, Predictor(model, state, cfg.extrapolation), points[:n_plane], phys


def _distance(point, plane):
    return (plane - point).norm(dim=-1).min()


@pytest.mark.parametrize("t", [1.2, 2.0])
def test_a_painter_stops_where_it_would_leave_its_surface(t):
    model, predictor, plane, phys = _controlled_model(0.75)
    t0 = predictor.handover_time()
    start = model.deform(t0)["means"]
    with torch.no_grad():
        means = predictor.gaussians_at(t)["means"]
    n = len(plane)
    torch.testing.assert_close(means[:n], start[:n], rtol=0, atol=0)  # the plane, frozen
    carried = start + (t - t0) * phys
    torch.testing.assert_close(means[n:-2], carried[n:-2], rtol=0, atol=1e-5)  # the body
    torch.testing.assert_close(means[-1], carried[-1], rtol=0, atol=1e-5)  # B, on the plane
    # A: stopped on a step's position within reach of the plane, the next step out of it
    reach = 2 * max(float(_distance(start[-2], plane)), SPACING)
    h = (t - t0) / num_substeps(t - t0, model.dt_max)
    a = means[-2]
    assert 0 < float(a[2]) <= reach + 1e-6, a  # it moved up before stopping
    torch.testing.assert_close(a[:2], start[-2, :2], rtol=0, atol=1e-5)
    k = float(a[2]) / h
    assert abs(k - round(k)) < 1e-4  # on a step
    assert float(_distance(a, plane)) <= reach < float(_distance(a + h * UP, plane))


@pytest.mark.parametrize("t", [1.2, 2.0])
def test_held_painters_keep_their_handover_state(t):
    model, predictor, plane, phys = _controlled_model(0.75, painters="hold")
    t0 = predictor.handover_time()
    start = model.deform(t0)
    with torch.no_grad():
        now = predictor.gaussians_at(t)
    n = len(plane)
    torch.testing.assert_close(now["means"][:n], start["means"][:n], rtol=0, atol=0)  # the plane, frozen
    carried = start["means"] + (t - t0) * phys
    torch.testing.assert_close(now["means"][n:-2], carried[n:-2], rtol=0, atol=1e-5)  # the body
    torch.testing.assert_close(now["means"][-2:], start["means"][-2:], rtol=0, atol=0)  # A and B
    torch.testing.assert_close(now["quats"][-2:], start["quats"][-2:], rtol=0, atol=1e-6)


def test_the_stop_is_the_same_for_every_later_time():
    model, predictor, plane, _ = _controlled_model(0.75)
    with torch.no_grad():
        late = [predictor.gaussians_at(t)["means"][-2] for t in (1.5, 2.5)]
    torch.testing.assert_close(late[0], late[1], rtol=0, atol=1e-5)


def test_off_the_physics_carries_every_painter():
    model, predictor, plane, phys = _controlled_model(0.0)
    t0 = predictor.handover_time()
    start = model.deform(t0)["means"]
    with torch.no_grad():
        means = predictor.gaussians_at(1.2)["means"]
    n = len(plane)
    torch.testing.assert_close(means[n:], (start + (1.2 - t0) * phys)[n:], rtol=0, atol=1e-5)


def test_without_still_gaussians_nothing_stops():
    model, predictor, plane, phys = _controlled_model(0.5)
    predictor.state.freeze_threshold = 0.0  # nobody frozen: the plane "moves" with zero velocity
    t0 = predictor.handover_time()
    start = model.deform(t0)["means"]
    with torch.no_grad():
        means = predictor.gaussians_at(1.2)["means"]
    torch.testing.assert_close(means, start + (1.2 - t0) * phys, rtol=0, atol=1e-5)
