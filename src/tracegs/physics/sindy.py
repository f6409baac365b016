"""The pieces of an identified motion model ``q'' = f(q, q')`` (``physics/identify.py``): the library
of candidate terms, the sparse regression that picks among them, the integration of a model forward
in time (with contacts), and the shooting fit that makes its constants exact.

A model is a matrix ``Xi`` [n, F]: coordinate ``i`` accelerates by ``sum_f Xi[i, f] theta_f(q, q')``,
the ``theta_f`` the library's terms (``TERM_KINDS``). Sparse regression on the path's smoothed
derivatives (SINDy: PySINDy's ``STLSQ``, sequentially thresholded least squares) chooses which terms
are non-zero; derivatives of a sampled path are biased (smoothing flattens the peaks of ``q''``), so
the constants of the chosen terms, with the initial state, are then fitted to the samples themselves
through the integrated trajectory (shooting, ``scipy.optimize.least_squares``): the maximum-likelihood
fit for independent noise on ``q``, exact on an exact path. PySINDy's ``SINDy`` model object is not
used: it regresses every state derivative, the trivial ``q' = q'`` rows of a second-order system
included, and its libraries apply each function to every coordinate, where ``sin`` and ``cos`` belong
to angular coordinates only; the optimizer is the part it does well.

n: coordinates, F: library terms, B: models integrated together (a batch), T: samples. numpy float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .force_law import rk4_step

Array = np.ndarray

TERM_KINDS = ("1", "q", "v", "sin", "cos", "sign", "drag")
"""The kinds of term, simplest first: a constant (gravity, a constant force), ``q_i`` and ``q_i'``
(springs, damping, the coupling between coordinates), ``sin q_i`` and ``cos q_i`` of an angular
coordinate (a pendulum), ``sign q_i'`` (Coulomb friction) and ``q_i' |q_i'|`` (quadratic drag)."""

Term = tuple[str, int]
"""A library term: its kind and its coordinate (-1 for the constant)."""


def library_terms(n: int, angular: tuple[bool, ...], friction: bool = True, drag: bool = True) -> list[Term]:
    """The candidate terms for ``n`` coordinates, simplest first (``TERM_KINDS`` order), ``sin`` and
    ``cos`` only of the coordinates that ``angular`` [n] marks."""
    terms: list[Term] = [("1", -1)]
    for kind in TERM_KINDS[1:]:
        if (kind == "sign" and not friction) or (kind == "drag" and not drag):
            continue
        terms += [(kind, i) for i in range(n) if kind not in ("sin", "cos") or angular[i]]
    return terms


def term_name(term: Term) -> str:
    """A term as it reads in an equation: ``1``, ``q0``, ``q0'``, ``sin q0``, ``sign q0'``, ``q0'|q0'|``."""
    kind, i = term
    return {
        "1": "1",
        "q": f"q{i}",
        "v": f"q{i}'",
        "sin": f"sin q{i}",
        "cos": f"cos q{i}",
        "sign": f"sign q{i}'",
        "drag": f"q{i}'|q{i}'|",
    }[kind]


def evaluate(terms: list[Term], q: Array, v: Array) -> Array:
    """[..., F] the terms at the states ``q``, ``v`` [..., n]."""
    functions = {
        "1": lambda x: np.ones_like(x),
        "q": lambda x: x,
        "v": lambda x: x,
        "sin": np.sin,
        "cos": np.cos,
        "sign": np.sign,
        "drag": lambda x: x * np.abs(x),
    }
    return np.stack(
        [
            functions[kind](v[..., max(i, 0)] if kind in ("v", "sign", "drag") else q[..., max(i, 0)])
            for kind, i in terms
        ],
        -1,
    )


def equation(i: int, terms: list[Term], row: Array) -> str:
    """Coordinate ``i``'s equation with the coefficients ``row`` [F], e.g. ``q0'' = -9.81 - 0.31 q0'``."""
    parts = []
    for term, c in zip(terms, row, strict=True):
        if c == 0:
            continue
        sign = "-" if c < 0 else "+"
        value = f"{abs(c):.6g}" + ("" if term[0] == "1" else " " + term_name(term))
        parts.append(value if not parts and c > 0 else f"{sign} {value}" if parts else f"-{value}")
    return f"q{i}'' = " + (" ".join(parts) if parts else "0")


def smoothed_derivatives(t: Array, q: Array) -> tuple[Array, Array, Array]:
    """``(q, q', q'')`` [T, n] of a smoothing spline per coordinate (smoothness by generalised
    cross-validation)."""
    from scipy.interpolate import make_smoothing_spline

    splines = [make_smoothing_spline(t, q[:, i]) for i in range(q.shape[1])]
    return tuple(np.stack([s(t, k) for s in splines], 1) for k in range(3))


def independent_terms(theta: Array, tol: float = 1e-3) -> Array:
    """[F] bool: the columns of ``theta`` [T, F] kept in order while each adds a direction of relative
    size above ``tol`` to those kept before it. Terms the samples cannot tell apart (``sin q`` from ``q``
    at small angles, ``sign q'`` from the constant while ``q'`` keeps one sign) would split their
    coefficient at random; the simpler one (earlier in ``TERM_KINDS``) stays."""
    kept, basis = np.zeros(theta.shape[1], dtype=bool), []
    for f in range(theta.shape[1]):
        x = theta[:, f].astype(np.float64)
        norm = np.linalg.norm(x)
        for b in basis:
            x = x - (b @ x) * b
        if norm > 0 and np.linalg.norm(x) > tol * norm:
            kept[f] = True
            basis.append(x / np.linalg.norm(x))
    return kept


def stlsq(theta: Array, target: Array, threshold: float, ridge: float = 1e-6) -> Array:
    """[n, F] the sparse coefficients of ``target`` [T, n] on ``theta`` [T, F] by PySINDy's ``STLSQ``:
    the columns scaled to unit RMS and each target to unit RMS, so ``threshold`` is the smallest share
    of a coordinate's acceleration a term may explain; coefficients returned in the original units."""
    import pysindy as ps

    scale = np.sqrt(np.mean(theta**2, 0)) + 1e-300
    target_scale = np.sqrt(np.mean(target**2, 0)) + 1e-300
    optimizer = ps.STLSQ(threshold=threshold, alpha=ridge * len(theta), unbias=True)
    optimizer.fit(theta / scale, target / target_scale)
    return np.asarray(optimizer.coef_).reshape(target.shape[1], -1) * target_scale[:, None] / scale


@dataclass(frozen=True)
class Contact:
    """A surface the coordinate ``coordinate`` bounces on: moving in ``direction`` (+1 or -1) it stops
    at ``position``, its velocity reversed and scaled by the restitution ``restitution``."""

    coordinate: int
    position: float
    direction: int
    restitution: float


def _acceleration(terms: list[Term], xi: Array, q: Array, v: Array) -> Array:
    """[B, n] the models ``xi`` [B, n, F] at the states ``q``, ``v`` [B, n]."""
    return np.einsum("bnf,bf->bn", xi, evaluate(terms, q, v))


def _rk4(terms: list[Term], xi: Array, q: Array, v: Array, h: Array) -> tuple[Array, Array]:
    """One RK4 step (``force_law.rk4_step``) of ``h`` [B, 1] of the states ``q``, ``v`` [B, n]."""
    return rk4_step(lambda q, v, x: _acceleration(terms, x, q, v), q, v, xi, h)


def _stick(terms: list[Term], xi: Array, q0, v0, q1, v1, h) -> tuple[Array, Array]:
    """The step from ``(q0, v0)`` to ``(q1, v1)`` [B, n] with Coulomb friction (a ``sign q_i'`` term):
    a coordinate at rest, or whose velocity reaches zero within the step (where: its velocity taken as
    linear over the step), stays there while the rest of its acceleration is within the friction's
    (it sticks); RK4 across ``sign``'s jump would chatter about the stop."""
    friction = np.zeros(xi.shape[:2])  # [B, n] each coordinate's coefficient of its own sign q_i'
    for f, (kind, i) in enumerate(terms):
        if kind == "sign":
            friction[:, i] = np.abs(xi[:, i, f])
    if not friction.any():
        return q1, v1
    sign_free = xi * np.array([kind != "sign" for kind, _ in terms])
    crossed = (friction > 0) & (v0 * v1 < 0)
    s = np.where(crossed, v0 / np.where(crossed, v0 - v1, 1.0), 1.0)  # the step's fraction to v = 0
    stop = np.where(crossed, q0 + 0.5 * v0 * s * h, q1)
    resting = crossed | ((friction > 0) & (v0 == 0))
    if resting.any():
        at = np.where(crossed, stop, q0)
        push = _acceleration(terms, sign_free, at, np.where(resting, 0.0, v0))  # the rest, at rest
        held = resting & (np.abs(push) <= friction)
        q1, v1 = np.where(held, at, q1), np.where(held, 0.0, v1)
    return q1, v1


def _bounce(terms, xi, q0, v0, q1, v1, h, contact: Contact) -> tuple[Array, Array]:
    """The step from ``(q0, v0)`` to ``(q1, v1)`` [B, n] redone for the rows that cross ``contact``: to
    the crossing (the step's fraction by two secant steps), the velocity reversed there, then on."""
    i, d = contact.coordinate, contact.direction
    rows = (d * (q1[:, i] - contact.position) > 0) & (d * (q0[:, i] - contact.position) <= 0)
    if not rows.any():
        return q1, v1
    qa, va, hr, x = q0[rows], v0[rows], h[rows], xi[rows]
    gap0, gap1 = qa[:, i] - contact.position, q1[rows, i] - contact.position
    s = np.clip(gap0 / (gap0 - gap1), 0.0, 1.0)
    for _ in range(2):
        qs, _ = _rk4(terms, x, qa, va, s[:, None] * hr)
        slope = np.where(s > 0, (qs[:, i] - qa[:, i]) / np.maximum(s, 1e-12), qs[:, i] - qa[:, i])
        slope = np.where(np.abs(slope) > 1e-300, slope, 1e-300)
        s = np.clip(s - (qs[:, i] - contact.position) / slope, 0.0, 1.0)
    qc, vc = _rk4(terms, x, qa, va, s[:, None] * hr)
    qc[:, i] = contact.position
    vc[:, i] = -contact.restitution * vc[:, i]
    qe, ve = _rk4(terms, x, qc, vc, (1 - s)[:, None] * hr)
    # bounced too weakly to leave the surface within the step (the bounces of a restitution below 1
    # shorten geometrically and end in finite time): at rest on it
    rest = d * (qe[:, i] - contact.position) > 0
    qe[rest, i], ve[rest, i] = contact.position, 0.0
    q1, v1 = q1.copy(), v1.copy()
    q1[rows], v1[rows] = qe, ve
    return q1, v1


def integrate(
    terms: list[Term],
    xi: Array,
    q0: Array,
    v0: Array,
    s: Array,
    dt_max: float,
    contacts: tuple[Contact, ...] = (),
) -> tuple[Array, Array]:
    """``(q, v)`` [B, T, n] of the models ``xi`` [B, n, F] from the states ``q0``, ``v0`` [B, n] at time 0
    to the increasing times ``s`` [T] >= 0, by RK4 steps of at most ``dt_max``, bouncing on
    ``contacts``. Rows that blow up turn non-finite and stay so."""
    q, v = np.array(q0, dtype=np.float64), np.array(v0, dtype=np.float64)
    out_q, out_v = np.empty((len(q), len(s), q.shape[1])), np.empty((len(q), len(s), q.shape[1]))
    now = 0.0
    with np.errstate(all="ignore"):
        for k, target in enumerate(np.asarray(s, dtype=np.float64)):
            steps = max(0, math.ceil((target - now) / dt_max - 1e-9))
            h = np.full((len(q), 1), (target - now) / max(steps, 1))
            for _ in range(steps):
                q1, v1 = _stick(terms, xi, q, v, *_rk4(terms, xi, q, v, h), h)
                for contact in contacts:
                    q1, v1 = _bounce(terms, xi, q, v, q1, v1, h, contact)
                q, v = q1, v1
            now = max(now, float(target))
            out_q[:, k], out_v[:, k] = q, v
    return out_q, out_v


def shoot(
    terms: list[Term],
    xi: Array,
    active: Array,
    pieces: list[tuple[Array, Array, Array, Array]],
    dt_max: float,
) -> tuple[Array, list[tuple[Array, Array]], float, Array]:
    """``(xi [n, F], [(q0, v0) [n]], rms, significance [n, F])``: the coefficients ``active`` [n, F] bool of ``xi``, shared by
    the pieces, and each piece's initial state fitted to its samples through the integrated
    trajectories (Levenberg-Marquardt from the given values), the RMS residual over all samples, and
    each fitted coefficient's significance: its square over its variance in the linearised fit (the
    Wald statistic: how much the squared residual grows, in units of the noise, when it is set to
    zero; low for a term the samples cannot tell from the others; zeros elsewhere).
    ``pieces``: ``(t [T], q [T, n], q0 [n], v0 [n])`` each, the samples ``q`` at the times ``t`` and a
    first guess of the state at ``t[0]`` (the paths between contacts: one law, a state each)."""
    from scipy.optimize import least_squares

    n, m = xi.shape[0], 2 * xi.shape[0] * len(pieces)
    samples = np.concatenate([q.reshape(-1) for _, q, _, _ in pieces])

    def trajectories(x: Array) -> Array:  # x [B, m + P] -> [B, samples]
        full = np.broadcast_to(xi, (len(x), *xi.shape)).copy()
        full[:, active] = x[:, m:]
        paths = []
        for k, (t, _, _, _) in enumerate(pieces):
            state = x[:, 2 * n * k : 2 * n * (k + 1)]
            path, _ = integrate(terms, full, state[:, :n], state[:, n:], t - t[0], dt_max)
            paths.append(path.reshape(len(x), -1))
        return np.nan_to_num(np.concatenate(paths, 1), nan=1e12, posinf=1e12, neginf=-1e12)

    def residual(x: Array) -> Array:
        return trajectories(x[None])[0] - samples

    def jacobian(x: Array) -> Array:
        h = 1e-7 * np.maximum(np.abs(x), 1e-4 * (1 + np.abs(x).max()))
        rows = trajectories(np.vstack([x, x + np.diag(h)]))
        return ((rows[1:] - rows[0]) / h[:, None]).T

    x0 = np.concatenate([np.concatenate([q0, v0]) for _, _, q0, v0 in pieces] + [xi[active]])
    with np.errstate(all="ignore"):  # a set of terms whose rollout blows up is scored as such, not warned of
        fit = least_squares(residual, x0, jac=jacobian, method="lm", x_scale="jac", max_nfev=50 * len(x0))
        r = residual(fit.x)
        noise = float(r @ r) / max(len(r) - len(fit.x), 1) + 1e-300
        information = fit.jac.T @ fit.jac
        rms = float(np.sqrt(np.mean(r**2)))
    full, significance = xi.copy(), np.zeros(xi.shape)
    full[active] = fit.x[m:]
    try:  # (a fit that blew up says nothing of its terms' significance: zeros)
        if np.isfinite(information).all() and np.isfinite(fit.x).all():
            variance = np.diag(np.linalg.pinv(information))[m:] * noise
            significance[active] = fit.x[m:] ** 2 / np.maximum(variance, 1e-300)
    except np.linalg.LinAlgError:
        pass
    states = [
        (fit.x[2 * n * k : 2 * n * k + n], fit.x[2 * n * k + n : 2 * n * (k + 1)]) for k in range(len(pieces))
    ]
    return full, states, rms, significance
