"""Thrown parts: a spinning ball that f_defo bounces on a floor gets the bounce law's gravity,
restitution and floor, its drift and its spin from its path, and after the handover it bounces on
as the truth does, past contacts no training frame shows; a part that flies on a straight line is
no thrown part."""

import numpy as np
import torch
from tests.conftest import blob_model

from tracegs.extrapolate import calibrate
from tracegs.extrapolate.thrown import fit_thrown
from tracegs.physics.force_law import LAWS, integrate
from tracegs.physics.free_body import centre_of_mass, main_piece
from tracegs.physics.so3 import rodrigues

G, E, FLOOR = 8.0, 0.7, -0.34  # the floor of the centre's height (a ball's radius above the ground)
DRIFT = torch.tensor([0.35, 0.0, 0.0], dtype=torch.float64)
SPIN = torch.tensor([0.0, 3.0, 0.0], dtype=torch.float64)
UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
START = torch.tensor([-0.45, 0.0, -0.14], dtype=torch.float64)  # 0.2 above its floor: a contact at 0.224


def height(t: float) -> float:
    """The centre's height: dropped from rest, bouncing (exact steps of the law)."""
    q, _ = integrate(LAWS["bounce"], np.array([[G, E, FLOOR]]), [float(START[2])], [0.0], [t], 1e-3)
    return float(q[0, 0])


def ball(t: float, start: torch.Tensor = START) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R, T)`` of the ball from t = 0: spun about its centre, at ``start`` at t = 0, which drifts
    and bounces (its floor ``start`` - ``START`` above ``FLOOR``)."""
    turn = rodrigues(SPIN * t)
    centre = start + DRIFT * t + UP * (height(t) - float(START[2]))
    return turn, centre - turn @ start


def surface(n: int = 4000, radius: float = 0.16, seed: int = 1) -> torch.Tensor:
    """[M, 3] points on a sphere about the origin, three times as dense on its +z half as on its -z
    half (the cameras saw one side better): their mean is 0.04 above the centre."""
    gen = torch.Generator().manual_seed(seed)
    u = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True)
    keep = (u[:, 2] > 0) | (torch.rand(n, generator=gen, dtype=torch.float64) < 1 / 3)
    return radius * u[keep]


def test_fit_thrown_recovers_the_bounce_the_drift_and_the_spin():
    offsets = surface()
    assert float(offsets.mean(0).norm()) > 0.04  # the points' mean is not the centre
    times = np.linspace(0.0, 0.75, 31)
    path = torch.stack([(START + offsets) @ ball(t)[0].T + ball(t)[1] for t in times])
    fit = fit_thrown(path, times)
    assert fit is not None and abs(fit["contact"] - 0.2236) < 0.01
    centre = torch.stack([START + DRIFT * t + UP * (height(t) - float(START[2])) for t in times])
    assert float((torch.from_numpy(fit["centres"]) - centre).norm(dim=1).max()) < 2e-3
    torch.testing.assert_close(fit["centre"], centre[-1], atol=2e-3, rtol=0)
    constants = fit["law"].constants
    assert abs(constants["g"] - G) < 0.01 * G and abs(constants["e"] - E) < 0.01
    assert abs(constants["floor"] - FLOOR) < 2e-3
    assert abs(float(torch.from_numpy(fit["axis"]) @ UP)) > 1 - 1e-4
    torch.testing.assert_close(torch.from_numpy(fit["velocity"]), DRIFT, atol=5e-3, rtol=0)
    torch.testing.assert_close(fit["spin"], SPIN, atol=1e-6, rtol=0)
    straight = torch.stack([START + offsets + DRIFT * t for t in times])
    assert fit_thrown(straight, times) is None


def test_a_bouncing_ball_bounces_on_after_the_handover():
    centre = {}  # a body turns about its centre of mass: the centroid of the blob's hull, not its mean
    model, settings, (thrown, floor) = blob_model(
        [tuple(START.tolist()), (0.0, 0.0, -0.8)], [lambda t: ball(t, centre["c"]), None]
    )
    blob = model.gaussians["means"][thrown].detach()
    centre["c"] = centre_of_mass(blob[main_piece(blob)])
    t_max = 0.75
    predictor = calibrate(model, t_max, settings, extent=2.0)
    state = predictor.state
    entry = next(e for e in state.report["joint_laws"] if e.get("model") == "thrown")
    assert entry["adopted"] and entry["law"] == "bounce", entry
    assert abs(entry["constants"]["e"] - E) < 0.02 and abs(entry["constants"]["g"] - G) < 0.02 * G
    assert torch.equal(state.joint_laws["labels"] > 0, thrown)
    start = model.deform(predictor.handover_time())["means"]
    for t in (0.9, 1.0, 1.3):  # past contacts at 0.76, 0.91 and 1.02, after the handover at 0.55
        got, want = predictor.gaussians_at(t)["means"], model.deform(t)["means"]
        error = float((got[thrown] - want[thrown]).norm(dim=1).max())
        assert error < 0.01, (t, error)
        torch.testing.assert_close(got[floor], start[floor])
    # off, the learned physics (zero here) leaves the ball where the handover put it
    predictor.settings.joint_laws = False
    torch.testing.assert_close(predictor.gaussians_at(1.0)["means"], start)
