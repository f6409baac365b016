"""Force laws of a one-dimensional generalised coordinate, and their integration forward in time.

A rigid part on a hinge or a rail has one degree of freedom: its joint angle, or its position along
the rail, ``q(t)`` (``physics/joint.py`` turns its transforms into ``q`` and back). A force law says
how it accelerates from its state: ``q'' = f(q, q')``, with a few constants. TRACE holds the
acceleration constant (``constant``); the others keep predicting when the force changes with the state:

- ``constant``: ``q'' = a``;
- ``friction_stop``: ``q'' = -mu sign(q')`` while ``q' != 0``, then ``q' = 0`` for good (Coulomb
  friction: a wheel braking to rest, a drawer that stops);
- ``spring_damper``: ``q'' = -k (q - q_rest) - c q'`` (a mass on a spring, a pendulum at small angles);
- ``pendulum``: ``q'' = -k sin(q - q_rest) - c q'``;
- ``bounce``: ``q'' = -g`` above a floor at ``q = floor``, the speed reversed and scaled by the
  restitution ``e`` at each contact (a translation coordinate along gravity).

Each law steps a batch of states with its own parameters (``ForceLaw.step``); ``integrate`` chains the
steps to the requested times whatever the law, as ``physics/integrate.py`` does for the particles.
Smooth laws step by RK4; the piecewise-constant laws step exactly, the stop or contact found in closed
form within the step, so a braking coordinate stops exactly at ``q' = 0`` and never chatters. The
closed-form solutions at the end are what the tests hold the integration to.

B: parameter sets stepped together (a batch), P: a law's parameters, T: times. numpy float64.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .integrate import num_substeps

Array = np.ndarray
Acceleration = Callable[[Array, Array, Array], Array]  # (q [B], v [B], p [B, P]) -> q'' [B]
Step = Callable[[Array, Array, Array, float], tuple[Array, Array]]  # (q, v, p, dt) -> (q, v)

MAX_CONTACTS = 32
"""Contacts resolved within one step of ``bounce``; a body still bouncing after them is at rest (the
bounces of a restitution below 1 shorten geometrically and end in finite time)."""


def rk4_step(acceleration: Acceleration, q: Array, v: Array, p: Array, dt: float) -> tuple[Array, Array]:
    """Classic RK4 on ``(q, v)' = (v, acceleration(q, v, p))`` for ``q``, ``v`` [B], ``p`` [B, P]."""
    a1 = acceleration(q, v, p)
    q2, v2 = q + 0.5 * dt * v, v + 0.5 * dt * a1
    a2 = acceleration(q2, v2, p)
    q3, v3 = q + 0.5 * dt * v2, v + 0.5 * dt * a2
    a3 = acceleration(q3, v3, p)
    q4, v4 = q + dt * v3, v + dt * a3
    a4 = acceleration(q4, v4, p)
    return q + dt / 6 * (v + 2 * v2 + 2 * v3 + v4), v + dt / 6 * (a1 + 2 * a2 + 2 * a3 + a4)


def constant_acceleration(q: Array, v: Array, p: Array) -> Array:
    """``q'' = a``, ``p = (a,)``."""
    return p[:, 0] + 0 * q


def spring_damper_acceleration(q: Array, v: Array, p: Array) -> Array:
    """``q'' = -k q - c v + f``, ``p = (k, c, f)``: ``-k (q - q_rest) - c v`` with ``f = k q_rest``,
    which stays well posed as ``k -> 0`` (a constant force)."""
    return -p[:, 0] * q - p[:, 1] * v + p[:, 2]


def pendulum_acceleration(q: Array, v: Array, p: Array) -> Array:
    """``q'' = alpha sin q + beta cos q - c v``, ``p = (alpha, beta, c)``: ``-k sin(q - q_rest) - c v``
    with ``alpha = -k cos q_rest``, ``beta = k sin q_rest`` (linear in ``p``)."""
    return p[:, 0] * np.sin(q) + p[:, 1] * np.cos(q) - p[:, 2] * v


def friction_step(q: Array, v: Array, p: Array, dt: float) -> tuple[Array, Array]:
    """Exact step of ``q'' = -mu sign(q')``, ``p = (mu,)``: a parabola up to the stop at
    ``|v| / mu``, then at rest (``v`` exactly 0, which stays 0)."""
    mu = np.clip(p[:, 0], 0.0, None)
    direction = np.sign(v)
    with np.errstate(over="ignore"):  # (a tiny mu: the stop is past any step, inf as meant)
        t_stop = np.divide(np.abs(v), mu, out=np.full_like(v, np.inf), where=mu > 0)
    stops = t_stop <= dt
    s = np.where(stops, t_stop, dt)
    q_new = q + v * s - 0.5 * direction * mu * s * s
    return q_new, np.where(stops, 0.0, v - direction * mu * dt)


def bounce_step(q: Array, v: Array, p: Array, dt: float) -> tuple[Array, Array]:
    """Exact step of ``q'' = -g`` above ``floor``, ``p = (g, e, floor)``: each contact within the step
    is found in closed form (the later root of the parabola) and reverses the speed, times ``e``."""
    g, e, floor = np.clip(p[:, 0], 1e-12, None), np.clip(p[:, 1], 0.0, 1.0), p[:, 2]
    remaining = np.full_like(q, dt)
    rest = (q <= floor) & (v <= 0)
    for _ in range(MAX_CONTACTS):
        hits = ~rest & (q + v * remaining - 0.5 * g * remaining**2 < floor)
        if not hits.any():
            break
        s = (v + np.sqrt(np.clip(v * v + 2 * g * (q - floor), 0.0, None))) / g
        s = np.clip(s, 0.0, remaining)
        v_after = -e * (v - g * s)
        q, v = np.where(hits, floor, q), np.where(hits, v_after, v)
        remaining = np.where(hits, remaining - s, remaining)
        rest |= hits & (2 * v_after / g <= 1e-12 * max(dt, 1e-300))
    else:
        rest |= q + v * remaining - 0.5 * g * remaining**2 < floor
    q_new = q + v * remaining - 0.5 * g * remaining**2
    v_new = v - g * remaining
    return np.where(rest, floor, q_new), np.where(rest, 0.0, v_new)


def _smooth(acceleration: Acceleration) -> Step:
    return lambda q, v, p, dt: rk4_step(acceleration, q, v, p, dt)


def _lstsq(columns: list[Array], a: Array) -> Array:
    return np.linalg.lstsq(np.stack(columns, 1), a, rcond=None)[0]


def _guess_friction(q: Array, v: Array, a: Array) -> Array:
    moving = np.abs(v) > 0.2 * np.abs(v).max()
    mu = np.median(-a[moving] * np.sign(v[moving])) if moving.any() else 0.0
    return np.array([max(float(mu), 1e-6)])


def _guess_bounce(q: Array, v: Array, a: Array) -> Array:
    floor = float(q.min())
    flying = q > floor + 0.1 * (q.max() - floor)
    g = np.median(-a[flying]) if flying.any() else 1.0
    return np.array([max(float(g), 1e-6), 0.8, floor])


def _spring_constants(p: Array, t0: float, q0: float, v0: float) -> dict[str, float]:
    k = float(p[0])
    return {"k": k, "c": float(p[1]), "q_rest": float(p[2]) / k if k != 0 else math.nan}


def _pendulum_constants(p: Array, t0: float, q0: float, v0: float) -> dict[str, float]:
    return {"k": math.hypot(p[0], p[1]), "c": float(p[2]), "q_rest": math.atan2(p[1], -p[0])}


def _friction_constants(p: Array, t0: float, q0: float, v0: float) -> dict[str, float]:
    mu = float(p[0])
    return {"mu": mu, "t_stop": t0 + abs(v0) / mu if mu > 0 else math.inf}


@dataclass(frozen=True)
class ForceLaw:
    """A law ``q'' = f(q, q')`` with ``P`` parameters (``parameters``): how to step it, a first guess
    of its parameters by linear least squares on a trajectory's derivatives, and its constants."""

    name: str
    parameters: tuple[str, ...]
    step: Step
    guess: Callable[[Array, Array, Array], Array]  # (q [T], v [T], a [T]) -> p [P]
    constants: Callable[[Array, float, float, float], dict[str, float]]  # (p, t0, q0, v0)
    lower: tuple[float, ...]
    upper: tuple[float, ...]


_FREE = -np.inf, np.inf
LAWS: dict[str, ForceLaw] = {
    law.name: law
    for law in (
        ForceLaw(
            "constant",
            ("a",),
            _smooth(constant_acceleration),
            lambda q, v, a: np.array([a.mean()]),
            lambda p, t0, q0, v0: {"a": float(p[0])},
            (-np.inf,),
            (np.inf,),
        ),
        ForceLaw(
            "friction_stop", ("mu",), friction_step, _guess_friction, _friction_constants, (0.0,), (np.inf,)
        ),
        ForceLaw(
            "spring_damper",
            ("k", "c", "f"),
            _smooth(spring_damper_acceleration),
            lambda q, v, a: _lstsq([-q, -v, np.ones_like(q)], a),
            _spring_constants,
            (_FREE[0],) * 3,
            (_FREE[1],) * 3,
        ),
        ForceLaw(
            "pendulum",
            ("alpha", "beta", "c"),
            _smooth(pendulum_acceleration),
            lambda q, v, a: _lstsq([np.sin(q), np.cos(q), -v], a),
            _pendulum_constants,
            (_FREE[0],) * 3,
            (_FREE[1],) * 3,
        ),
        ForceLaw(
            "bounce",
            ("g", "e", "floor"),
            bounce_step,
            _guess_bounce,
            lambda p, t0, q0, v0: {"g": float(p[0]), "e": float(p[1]), "floor": float(p[2])},
            (0.0, 0.0, -np.inf),
            (np.inf, 1.0, np.inf),
        ),
    )
}
"""The force laws by name, simplest first (the order in which near-ties are broken)."""


def integrate(law: ForceLaw, p: Array, q0: Array, v0: Array, s: Array, dt_max: float) -> tuple[Array, Array]:
    """``(q, v)`` [B, T] of the states ``q0``, ``v0`` [B] moved by ``law`` with parameters ``p``
    [B, P] to the times ``s`` [T] after the start (sorted, >= 0), in steps of at most ``dt_max``."""
    q, v = np.asarray(q0, dtype=np.float64).copy(), np.asarray(v0, dtype=np.float64).copy()
    p = np.asarray(p, dtype=np.float64)
    qs, vs = np.empty((len(q), len(s))), np.empty((len(q), len(s)))
    now = 0.0
    for i, target in enumerate(np.asarray(s, dtype=np.float64)):
        if target < now - 1e-12:
            raise ValueError(f"times must be sorted and after the start, got {target} after {now}")
        gap = target - now
        if gap > 0:
            n = num_substeps(gap, dt_max)
            for _ in range(n):
                q, v = law.step(q, v, p, gap / n)
            now = target
        qs[:, i], vs[:, i] = q, v
    return qs, vs


# Closed forms, from the state (q0, v0) at s = 0.


def constant_acceleration_solution(q0: float, v0: float, a: float, s: Array) -> Array:
    """[T] ``q0 + v0 s + a s^2 / 2``."""
    return q0 + v0 * s + 0.5 * a * s * s


def friction_stop_solution(q0: float, v0: float, mu: float, s: Array) -> Array:
    """[T] ``q0 + v0 s - sign(v0) mu s^2 / 2`` up to ``t_stop = |v0| / mu``, then constant."""
    s = np.minimum(s, abs(v0) / mu)
    return q0 + v0 * s - 0.5 * math.copysign(mu, v0) * s * s


def spring_damper_solution(q0: float, v0: float, k: float, c: float, q_rest: float, s: Array) -> Array:
    """[T] the linear spring-damper from ``(q0, v0)``: underdamped (``k > c^2/4``), critically damped
    (``k == c^2/4``) or overdamped, about ``q_rest``."""
    x0, gamma, disc = q0 - q_rest, 0.5 * c, 0.25 * c * c - k
    if disc < 0:
        omega = math.sqrt(-disc)
        x = np.exp(-gamma * s) * (x0 * np.cos(omega * s) + (v0 + gamma * x0) / omega * np.sin(omega * s))
    elif disc == 0:
        x = np.exp(-gamma * s) * (x0 + (v0 + gamma * x0) * s)
    else:
        r1, r2 = -gamma + math.sqrt(disc), -gamma - math.sqrt(disc)
        a1 = (v0 - r2 * x0) / (r1 - r2)
        x = a1 * np.exp(r1 * s) + (x0 - a1) * np.exp(r2 * s)
    return q_rest + x


def pendulum_solution(amplitude: float, k: float, q_rest: float, s: Array) -> Array:
    """[T] the undamped pendulum released from rest at ``q_rest + amplitude`` (``|amplitude| < pi``):
    ``q_rest + 2 arcsin(m sn(K(m^2) - sqrt(k) s | m^2))``, ``m = sin(amplitude / 2)``."""
    from scipy.special import ellipj, ellipk

    m = math.sin(0.5 * amplitude)
    sn = ellipj(ellipk(m * m) - math.sqrt(k) * np.asarray(s), m * m)[0]
    return q_rest + 2 * np.arcsin(m * sn)
