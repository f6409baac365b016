"""Force laws of a coordinate: each integrates to its closed form, identification recovers known
constants from exact and noisy samples, and the selection on the span's end picks the true law."""

import warnings

import numpy as np
import pytest

from tracegs.physics.force_law import (
    LAWS,
    constant_acceleration_solution,
    friction_step,
    friction_stop_solution,
    integrate,
    pendulum_solution,
    spring_damper_solution,
)
from tracegs.physics.force_law_fit import (
    fit_law,
    smoothed_derivatives,
)

T = np.linspace(0.0, 1.0, 61)  # 60 frames over the span


def integrated(name: str, params, q0: float, v0: float, s, dt_max: float = 1e-3) -> np.ndarray:
    return integrate(LAWS[name], np.array([params], dtype=float), [q0], [v0], s, dt_max)[0][0]


@pytest.mark.parametrize("c", [1.0, 2 * np.sqrt(50.0), 30.0])  # under-, critically, overdamped
def test_spring_damper_integrates_to_its_closed_form(c):
    k, q_rest = 50.0, 0.3
    want = spring_damper_solution(1.0, -2.0, k, c, q_rest, T)
    got = integrated("spring_damper", (k, c, k * q_rest), 1.0, -2.0, T)
    assert np.abs(got - want).max() < 1e-6 * np.abs(want - q_rest).max()


def test_constant_friction_and_pendulum_integrate_to_their_closed_forms():
    want = constant_acceleration_solution(0.2, 1.0, -3.0, T)
    assert np.abs(integrated("constant", (-3.0,), 0.2, 1.0, T) - want).max() < 1e-12
    for v0 in (2.0, -2.0):  # both directions
        want = friction_stop_solution(0.1, v0, 3.0, T)
        got, v = integrate(LAWS["friction_stop"], np.array([[3.0]]), [0.1], [v0], T, 1 / 60)
        assert np.abs(got[0] - want).max() < 1e-12
        assert np.all(v[0][T >= 2 / 3 + 1e-9] == 0)  # stopped exactly, and stays: no chatter
    want = pendulum_solution(2.0, 40.0, 0.1, T)  # a large swing: far from the linear spring
    assert (
        np.abs(integrated("pendulum", (-40 * np.cos(0.1), 40 * np.sin(0.1), 0.0), 2.1, 0.0, T) - want).max()
        < 1e-6 * 2.0
    )


def test_friction_too_small_to_stop_the_motion_holds_the_speed_without_a_warning():
    # mu so small that |v| / mu overflows: the stop lies past any step (a fit's constant near zero)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        q, v = friction_step(np.array([0.5]), np.array([2.0]), np.array([[1e-310]]), 0.1)
    assert q[0] == pytest.approx(0.5 + 2.0 * 0.1) and v[0] == pytest.approx(2.0)


def test_bounce_reverses_at_the_floor_with_the_restitution():
    g, e, h = 9.81, 0.6, 0.5
    s = np.linspace(0.0, 0.8, 161)
    q, v = integrate(LAWS["bounce"], np.array([[g, e, 0.0]]), [h], [0.0], s, 1 / 60)
    t_hit = np.sqrt(2 * h / g)
    up = e * g * t_hit  # the speed after the first contact
    after = s - t_hit
    want = np.where(s < t_hit, h - 0.5 * g * s**2, up * after - 0.5 * g * after**2)
    first_two_flights = s < t_hit + 2 * up / g
    assert np.abs(q[0] - want)[first_two_flights].max() < 1e-12
    assert q[0].min() >= 0.0
    rest = integrate(LAWS["bounce"], np.array([[g, 0.0, 0.0]]), [h], [0.0], s, 1 / 60)[0][0]
    assert np.all(rest[s > t_hit + 1e-9] == 0.0)  # no restitution: it lands and stays


def test_smoothed_derivatives_of_a_parabola():
    q, v, a = smoothed_derivatives(T, constant_acceleration_solution(0.0, 1.0, -2.0, T))
    assert np.abs(v[5:-5] - (1.0 - 2.0 * T[5:-5])).max() < 1e-3
    assert np.abs(a[10:-10] + 2.0).max() < 1e-2  # the spline's ends are natural (a = 0)


@pytest.mark.parametrize("c", [1.5, 12.0])  # a few swings; critically damped-ish
def test_spring_damper_constants_recovered_from_exact_samples(c):
    k, q_rest = 60.0, 0.2
    q = spring_damper_solution(1.0, 0.5, k, c, q_rest, T)
    fit = fit_law(T, q, "spring_damper").constants
    assert fit["k"] == pytest.approx(k, rel=1e-3)
    assert fit["c"] == pytest.approx(c, rel=1e-3)
    assert fit["q_rest"] == pytest.approx(q_rest, abs=1e-3)


def test_constants_recovered_from_noisy_samples():
    rng = np.random.default_rng(0)
    q = spring_damper_solution(1.0, 0.0, 60.0, 1.5, 0.2, T)
    noisy = q + 0.01 * rng.standard_normal(len(T))  # 1% of the amplitude
    fit = fit_law(T, noisy, "spring_damper")
    assert fit.constants["k"] == pytest.approx(60.0, rel=0.03)
    assert fit.constants["c"] == pytest.approx(1.5, rel=0.05)
    assert fit.rms == pytest.approx(0.01, rel=0.3)
    q = friction_stop_solution(0.1, 2.0, 3.0, T)
    fit = fit_law(T, q + 0.01 * rng.standard_normal(len(T)), "friction_stop").constants
    assert fit["mu"] == pytest.approx(3.0, rel=0.03)
    assert fit["t_stop"] == pytest.approx(2 / 3, rel=0.03)


def test_friction_pendulum_and_bounce_constants_recovered_from_exact_samples():
    fit = fit_law(T, friction_stop_solution(0.1, -2.0, 3.0, T), "friction_stop")
    assert fit.constants["mu"] == pytest.approx(3.0, rel=1e-6)
    assert fit.constants["t_stop"] == pytest.approx(2 / 3, rel=1e-6)
    fit = fit_law(T, pendulum_solution(1.5, 40.0, 0.1, T), "pendulum").constants
    assert fit["k"] == pytest.approx(40.0, rel=1e-3)
    assert fit["q_rest"] == pytest.approx(0.1, abs=1e-3)
    assert abs(fit["c"]) < 1e-3
    s = np.linspace(0.0, 1.2, 73)
    q = integrated("bounce", (9.81, 0.7, -0.1), 0.5, 0.3, s)
    fit = fit_law(s, q, "bounce").constants
    assert fit["g"] == pytest.approx(9.81, rel=1e-3)
    assert fit["e"] == pytest.approx(0.7, rel=1e-3)
    assert fit["floor"] == pytest.approx(-0.1, abs=1e-3)


def test_prediction_from_another_state_and_in_any_order():
    fit = fit_law(T, spring_damper_solution(1.0, 0.0, 60.0, 1.5, 0.2, T), "spring_damper")
    later = np.array([1.3, 1.1, 1.2])
    q, _ = fit.integrate_from(0.5, -1.0, 1.0, later)
    want = spring_damper_solution(0.5, -1.0, 60.0, 1.5, 0.2, later - 1.0)
    assert np.abs(q.numpy() - want).max() < 1e-5
    with pytest.raises(ValueError):
        fit.predict([-0.5])
