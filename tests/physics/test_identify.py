"""The identified motion model (physics/identify.py) against known dynamics: the constants of exact and
noisy paths, the chosen terms, the contacts, the verdict, and the rollout against closed forms."""

import io
import json

import numpy as np
import pytest
import torch
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from tracegs.physics.events import detect_events
from tracegs.physics.force_law import (
    constant_acceleration_solution,
    friction_stop_solution,
    pendulum_solution,
    spring_damper_solution,
)
from tracegs.physics.identify import IdentifiedModel, holdout_split, identify

FPS = 30.0


def _linear_path(k: np.ndarray, c: np.ndarray, x0: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[T, n] the exact path of ``q'' = -K q - C q'`` from ``x0 = (q, q')`` (matrix exponential)."""
    n = len(k)
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-k, -c]])
    return np.stack([expm(a * s) @ x0 for s in t])[:, :n]


def _relative(estimate: np.ndarray, truth: np.ndarray) -> float:
    """Largest error of a matrix's entries relative to its largest entry."""
    return float(np.abs(estimate - truth).max() / np.abs(truth).max())


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_coupled_damped_oscillator(noise):
    # two masses (1 and 2) on three springs, each damped: q'' = -M^-1 (S q + D q')
    mass = np.diag([1.0, 2.0])
    springs = np.array([[20.0 + 8.0, -8.0], [-8.0, 8.0 + 20.0]])
    damping = np.diag([0.4, 0.5])
    k, c = np.linalg.solve(mass, springs), np.linalg.solve(mass, damping)
    t = np.arange(60) / FPS
    q = _linear_path(k, c, np.array([0.3, -0.1, 0.0, 0.5]), t)
    q = q + noise * 0.3 * np.random.default_rng(0).standard_normal(q.shape)
    model = identify(t, q)
    stiffness, friction = model.linearised()
    assert model.adopted, model.why
    assert _relative(-stiffness, k) < 0.01
    assert _relative(-friction, c) < 0.02
    # the sparse model has the true terms only: springs and damping, no constant, friction or drag
    assert {kind for kind, _ in (model.terms[f] for f in np.flatnonzero(model.coefficients.any(0)))} == {
        "q",
        "v",
    }


def _double_pendulum(state, g=9.81, l1=1.0, l2=0.7, m1=1.0, m2=0.5):
    """``(q', q'')`` of the full (nonlinear) double pendulum, angles from the vertical."""
    a, b, va, vb = state
    d = a - b
    den = m1 + m2 * np.sin(d) ** 2
    aa = (
        -m2 * l1 * va**2 * np.sin(d) * np.cos(d)
        - m2 * l2 * vb**2 * np.sin(d)
        - (m1 + m2) * g * np.sin(a)
        + m2 * g * np.sin(b) * np.cos(d)
    ) / (l1 * den)
    bb = (
        (m1 + m2) * (l1 * va**2 * np.sin(d) - g * np.sin(b) + g * np.sin(a) * np.cos(d))
        + m2 * l2 * vb**2 * np.sin(d) * np.cos(d)
    ) / (l2 * den)
    return [va, vb, aa, bb]


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_double_pendulum_linear_regime(noise):
    g, l1, l2, m1, m2 = 9.81, 1.0, 0.7, 1.0, 0.5
    t = np.arange(75) / FPS
    sol = solve_ivp(
        lambda _, x: _double_pendulum(x), (0, t[-1]), [0.02, -0.03, 0, 0], t_eval=t, rtol=1e-12, atol=1e-14
    )
    q = sol.y[:2].T + noise * 0.03 * np.random.default_rng(5).standard_normal((len(t), 2))
    model = identify(t, q, angular=(True, True))
    # the linearised system q'' = -M^-1 G q: M the mass matrix at rest, G the gravity's stiffness
    m = np.array([[(m1 + m2) * l1**2, m2 * l1 * l2], [m2 * l1 * l2, m2 * l2**2]])
    truth = np.linalg.solve(m, np.diag([(m1 + m2) * g * l1, m2 * g * l2]))
    assert model.adopted, model.why
    assert _relative(-model.linearised()[0], truth) < 0.01


def test_pendulum_large_amplitude_chooses_sine():
    t = np.arange(60) / FPS
    sol = solve_ivp(
        lambda _, x: [x[1], -12.0 * np.sin(x[0]) - 0.3 * x[1]],
        (0, t[-1]),
        [2.0, 0.0],
        t_eval=t,
        rtol=1e-12,
        atol=1e-14,
    )
    model = identify(t, sol.y[0], angular=(True,))
    terms = [model.terms[f] for f in np.flatnonzero(model.coefficients[0])]
    assert model.adopted, model.why
    assert ("sin", 0) in terms and ("q", 0) not in terms
    sine = model.coefficients[0, model.terms.index(("sin", 0))]
    assert abs(sine + 12.0) < 0.12


def test_gravity_constant():
    t = np.arange(40) / FPS
    q = np.stack([2.0 + 0.5 * t, 3.0 + 1.5 * t - 0.5 * 9.81 * t**2], 1)
    q = q + 1e-4 * np.random.default_rng(1).standard_normal(q.shape)
    model = identify(t, q)
    assert model.adopted, model.why
    assert abs(model.coefficients[1, model.terms.index(("1", -1))] + 9.81) < 0.01 * 9.81
    assert abs(model.acceleration(q[-1], [0.5, 0.0])[0]) < 0.01


def _bounce(e: float, t: np.ndarray, h: float = 1.0, g: float = 9.81) -> tuple[np.ndarray, list[float]]:
    """The height of a ball dropped from ``h`` bouncing with restitution ``e``, and its impact times."""
    q, impacts, t0, v0, y0 = np.empty_like(t), [], 0.0, 0.0, h
    t_hit = (v0 + np.sqrt(v0**2 + 2 * g * y0)) / g
    for k, s in enumerate(t):
        while s > t0 + t_hit:
            impacts.append(t0 + t_hit)
            t0, v0, y0 = t0 + t_hit, e * g * t_hit - e * v0, 0.0
            t_hit = 2 * v0 / g
        q[k] = y0 + v0 * (s - t0) - 0.5 * g * (s - t0) ** 2
    return q, impacts


@pytest.mark.parametrize("noise", [0.0, 1e-3])
def test_bounce_event_and_restitution(noise):
    t = np.arange(50) / FPS
    q, impacts = _bounce(0.8, t)
    q = q + noise * np.random.default_rng(2).standard_normal(q.shape)
    events = detect_events(t, q)
    found = [e.time for e in events]
    assert len(events) == len(impacts) == 2
    assert np.abs(np.array(found) - impacts).max() < 1 / FPS
    for event in events:
        assert abs(event.restitution[0] - 0.8) < 0.02 * 0.8
    model = identify(t, q)
    assert len(model.contacts) == 1 and abs(model.contacts[0].position) < 0.01
    assert abs(model.coefficients[0, model.terms.index(("1", -1))] + 9.81) < 0.02 * 9.81
    # the model continues from after the last bounce, bouncing again on the floor
    later = t[-1] + np.arange(1, 40) / FPS
    truth, _ = _bounce(0.8, later)
    assert np.abs(model.rollout(later)[0][:, 0] - truth).max() < 0.03


@pytest.mark.parametrize("kind", ["jerky", "random_walk"])
def test_path_that_fits_no_model_is_not_adopted(kind):
    rng = np.random.default_rng(3)
    t = np.arange(60) / FPS
    if kind == "jerky":  # an acceleration drawn at random, held for five frames at a time
        a = np.repeat(rng.normal(0, 20.0, (12, 2)), 5, axis=0)
        q = np.cumsum(np.cumsum(a, 0) / FPS, 0) / FPS
    else:
        q = np.cumsum(rng.normal(0, 0.01, (60, 1)), 0)
    model = identify(t, q)
    assert not model.adopted
    assert model.why.startswith("not adopted: ")
    assert "held-out error" in model.why or "residual" in model.why


def test_learned_baseline_decides():
    k, c = np.array([[9.0]]), np.array([[0.3]])
    t = np.arange(60) / FPS
    q = _linear_path(k, c, np.array([0.2, 0.0]), t)
    n_fit = holdout_split(len(t))
    better = identify(t, q, baseline=q[n_fit:] + 0.05)
    perfect = identify(t, q, baseline=q[n_fit:])
    assert better.adopted and not perfect.adopted
    assert "baseline" in perfect.why


def test_rollout_matches_damped_oscillator_closed_form():
    omega, zeta = 2 * np.pi * 1.2, 0.08
    t = np.arange(60) / FPS
    wd = omega * np.sqrt(1 - zeta**2)

    def closed(s, a=0.25):  # q(0) = a, q'(0) = 0
        return a * np.exp(-zeta * omega * s) * (np.cos(wd * s) + zeta * omega / wd * np.sin(wd * s))

    model = identify(t, closed(t))
    assert model.adopted, model.why
    later = np.linspace(t[-1], t[-1] + 3.0, 200)
    assert np.abs(model.rollout(later)[0][:, 0] - closed(later)).max() < 1e-5 * 0.25
    assert abs(model.linearised()[0][0, 0] + omega**2) < 1e-5 * omega**2


def test_serialises_to_json_and_back():
    t = np.arange(40) / FPS
    q, _ = _bounce(0.7, t)
    model = identify(t, q)
    assert model.events  # (their times are where two quadratics meet: NumPy scalars until saved)
    back = IdentifiedModel.from_dict(json.loads(json.dumps(model.to_dict())))
    assert back.equations == model.equations and back.why == model.why and back.contacts == model.contacts
    buffer = io.BytesIO()  # a run's state is read back without unpickling code
    torch.save(model.to_dict(), buffer)
    buffer.seek(0)
    assert torch.load(buffer, weights_only=True) == json.loads(json.dumps(model.to_dict()))
    buffer = io.BytesIO()  # and so is what a run's summary says of it
    torch.save(model.report(), buffer)
    buffer.seek(0)
    assert torch.load(buffer, weights_only=True)["events"] == model.report()["events"]
    later = t[-1] + np.arange(1, 20) / FPS
    assert np.array_equal(back.rollout(later)[0], model.rollout(later)[0])


@pytest.mark.parametrize(
    ("law", "path"),
    [
        ("constant", lambda s: constant_acceleration_solution(0.0, 1.0, -1.5, s)),
        ("friction_stop", lambda s: friction_stop_solution(0.1, 2.0, 3.0, s)),  # stops at 0.67
        ("spring_damper", lambda s: spring_damper_solution(1.0, 0.0, 60.0, 1.5, 0.2, s)),
        ("pendulum", lambda s: pendulum_solution(2.0, 40.0, 0.0, s)),
    ],
)
def test_the_force_laws_are_special_cases(law, path):
    """The laws of ``physics/force_law.py`` are terms of the one model: identified from a span of each
    law's closed form (60 frames), its rollout matches the closed form on to twice the span."""
    t, future = np.linspace(0.0, 0.75, 46), np.linspace(0.75, 1.5, 16)
    model = identify(t, path(t), angular=(law == "pendulum",))
    assert model.adopted, model.why
    amplitude = float(np.ptp(path(np.concatenate([t, future]))))
    error = np.abs(model.rollout(future)[0][:, 0] - path(future)).max()
    assert error < 0.01 * amplitude, (model.equations, error)
