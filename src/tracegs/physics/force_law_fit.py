"""Fitting one force law of known form (``physics/force_law.py``) to samples of a coordinate ``q(t)``:
a thrown part's ``bounce`` (``extrapolate/thrown.py``); the model of a part's coordinates whose form
is not known is identified from a library of terms instead (``physics/identify.py``).

Identification is in two steps. First, a smoothing spline through the samples (its smoothness chosen
by generalised cross-validation) gives ``q'`` and ``q''``, and every law but the piecewise ones is
linear in its parameters, so linear least squares on them gives a first guess. Derivatives of noisy
samples are biased (the spline flattens the peaks, most of all in ``q''``), so this is only a start.
Second, shooting: ``scipy.optimize.least_squares`` fits the initial state and the parameters to the
samples themselves, through the integrated trajectory: the maximum-likelihood fit for independent
noise on ``q``, and exact on an exact trajectory. It needs the first step: shooting from a poor guess
of a frequency converges to another minimum.

T: times, P: a law's parameters. Inputs are tensors or arrays; outputs are float64 tensors.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .force_law import LAWS, ForceLaw, integrate


def _array(x) -> np.ndarray:
    return torch.as_tensor(x).detach().double().cpu().numpy().reshape(-1)


@dataclass(frozen=True)
class FittedLaw:
    """A force law with its parameters, and the state ``(q0, v0)`` it starts from at ``t0``."""

    name: str
    params: tuple[float, ...]
    t0: float
    q0: float
    v0: float
    rms: float
    """RMS residual of the samples it was fitted to."""
    dt_max: float
    """Largest integration step."""

    @property
    def law(self) -> ForceLaw:
        return LAWS[self.name]

    @property
    def constants(self) -> dict[str, float]:
        """The law's constants by name (e.g. ``k``, ``c``, ``q_rest``; ``mu`` with ``t_stop``)."""
        return self.law.constants(np.asarray(self.params), self.t0, self.q0, self.v0)

    def integrate_from(self, q: float, v: float, t_start: float, t) -> tuple[torch.Tensor, torch.Tensor]:
        """``(q, v)`` [T] at the times ``t`` [T] (any order, >= ``t_start``) of the state ``(q, v)`` at
        ``t_start`` moved by this law."""
        t = _array(t)
        if len(t) and t.min() < t_start - 1e-12:
            raise ValueError(f"times before the start {t_start}: {t.min()}")
        order = np.argsort(t, kind="stable")
        p = np.asarray(self.params)[None]
        qs, vs = integrate(self.law, p, [q], [v], np.maximum(t[order] - t_start, 0.0), self.dt_max)
        q_out, v_out = np.empty_like(t), np.empty_like(t)
        q_out[order], v_out[order] = qs[0], vs[0]
        return torch.from_numpy(q_out), torch.from_numpy(v_out)

    def state_at(self, t) -> tuple[torch.Tensor, torch.Tensor]:
        """``(q, v)`` [T] at the times ``t`` [T] (>= ``t0``) from the fitted start."""
        return self.integrate_from(self.q0, self.v0, self.t0, t)

    def predict(self, t) -> torch.Tensor:
        """[T] ``q`` at the times ``t`` (>= ``t0``)."""
        return self.state_at(t)[0]


def smoothed_derivatives(t, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(q, q', q'')`` [T] of a smoothing cubic spline through the samples ``q`` [T] at the increasing
    times ``t`` [T] (smoothness by generalised cross-validation; interpolating when T < 5)."""
    from scipy.interpolate import CubicSpline, make_smoothing_spline

    t, q = _array(t), _array(q)
    spline = make_smoothing_spline(t, q) if len(t) >= 5 else CubicSpline(t, q)
    return spline(t), spline(t, 1), spline(t, 2)


def _trajectories(law: ForceLaw, x: np.ndarray, s: np.ndarray, dt_max: float) -> np.ndarray:
    """[B, T] ``q`` at ``s`` of the rows of ``x`` [B, 2 + P] = (q0, v0, params); non-finite values
    (a trajectory that blew up) replaced by a large finite one, so the fit backs off from them."""
    q, _ = integrate(law, x[:, 2:], x[:, 0], x[:, 1], s, dt_max)
    return np.nan_to_num(q, nan=1e12, posinf=1e12, neginf=-1e12)


def fit_law(t, q, name: str, dt_max: float | None = None) -> FittedLaw:
    """The law ``name`` fitted to the samples ``q`` [T] at the increasing times ``t`` [T]: a first guess
    by linear least squares on the smoothed derivatives (``smoothed_derivatives``), then shooting on
    the samples (module docstring). ``dt_max``: the integration step, half the median sample spacing
    unless given."""
    from scipy.optimize import least_squares

    law = LAWS[name]
    t, q = _array(t), _array(q)
    if len(t) < 3 or np.any(np.diff(t) <= 0):
        raise ValueError("need at least 3 samples at increasing times")
    dt_max = float(dt_max or 0.5 * np.median(np.diff(t)))
    s = t - t[0]
    q_s, v_s, a_s = smoothed_derivatives(s, q)
    lower = np.array([-np.inf, -np.inf, *law.lower])
    upper = np.array([np.inf, np.inf, *law.upper])
    x0 = np.array([q_s[0], v_s[0], *law.guess(q_s, v_s, a_s)])
    width = np.where(np.isfinite(upper - lower), upper - lower, 1.0)
    x0 = np.clip(x0, lower + 1e-6 * width, upper - 1e-6 * width)

    def residual(x: np.ndarray) -> np.ndarray:
        return _trajectories(law, x[None], s, dt_max)[0] - q

    def jacobian(x: np.ndarray) -> np.ndarray:
        h = 1e-7 * np.maximum(np.abs(x), 1e-3)
        h = np.where(x + h > upper, -h, h)  # step inside the bounds
        rows = _trajectories(law, np.vstack([x, x + np.diag(h)]), s, dt_max)
        return ((rows[1:] - rows[0]) / h[:, None]).T

    fit = least_squares(
        residual,
        x0,
        jac=jacobian,
        bounds=(lower, upper),
        x_scale="jac",
        max_nfev=200,
        ftol=1e-12,
        xtol=1e-12,
        gtol=1e-12,
    )
    x = fit.x
    rms = float(np.sqrt(np.mean(residual(x) ** 2)))
    return FittedLaw(name, tuple(float(p) for p in x[2:]), float(t[0]), float(x[0]), float(x[1]), rms, dt_max)


def _split(t, q, holdout_fraction: float) -> int:
    """How many of the first samples are fitted: the rest, a ``holdout_fraction`` (at least one), is
    held out; at least 3 are fitted."""
    n = len(_array(t))
    held = max(1, round(holdout_fraction * n))
    if n - held < 3:
        raise ValueError(f"{n} samples are too few to hold out {held} and fit the rest")
    return n - held
