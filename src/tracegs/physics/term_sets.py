"""The candidate sets of library terms of a path and their fits (``physics/identify.py``): the path cut
into pieces at its events, each with its smoothed derivatives (``PathPieces``), and the sets of terms
that sparse regression keeps, dropped one at a time, or that best fit the derivatives, each fitted by
shooting once (``TermSets``).

n: coordinates, F: library terms, T: samples. numpy float64.
"""

from __future__ import annotations

import itertools

import numpy as np

from .events import Event, contacts_of, segments
from .sindy import (
    TERM_KINDS,
    Term,
    evaluate,
    independent_terms,
    integrate,
    shoot,
    smoothed_derivatives,
    stlsq,
    term_name,
)

Array = np.ndarray

MIN_PIECE = 3
"""Fewest samples of a piece of the path between events that the shooting fit uses."""
LIBRARIES = (None, ("1", "q", "v"), ("1", "v", "sin", "cos"))
"""The libraries the backward elimination starts from: every term, the linear ones (springs, coupled
masses, a chain at small angles) and the pendulum's; over a short span ``q`` and ``sin q`` are near
one another, and from every term the elimination can keep the wrong one."""
SMALL_SETS = 3
"""Of one coordinate, the sets of each number of library terms up to this one that best fit the
smoothed accelerations (``SMALL_SHOTS`` of each) are scored on the held-out end besides the nested sets of the
backward elimination."""
SMALL_SHOTS = 4
MIN_REGRESSION = 5
"""Fewest samples of a piece whose smoothed derivatives enter the regression."""
AT_REST = 0.02
"""A smoothed velocity below this fraction of the path's largest is rest in the regression."""


class PathPieces:
    """A path's pieces between events, each with its smoothed derivatives, up to a sample ``stop``."""

    def __init__(self, t: Array, q: Array, events: list[Event], stop: int):
        self.t, self.q = t, q
        self.pieces = []
        for start, end in segments(len(t), events):
            end = min(end, stop)
            if end - start >= MIN_PIECE:
                smooth = (
                    smoothed_derivatives(t[start:end], q[start:end])
                    if end - start >= MIN_REGRESSION
                    else None
                )
                self.pieces.append((start, end, smooth))
        self.contacts = contacts_of([e for e in events if e.after < stop], q[:stop])

    def regression(self, terms: list[Term]) -> tuple[Array, Array]:
        """``(theta [T, F], q'' [T, n])`` over the pieces long enough to smooth; a smoothed velocity
        within ``AT_REST`` of the path's largest counts as rest (``sign q'`` of a part that has stopped
        is 0, not the sign of the smoothing's ripple)."""
        smoothed = [s for _, _, s in self.pieces if s is not None]
        top = max((float(np.abs(s[1]).max()) for s in smoothed), default=0.0)
        rows = []
        for q, v, a in smoothed:
            theta = evaluate(terms, q, v)
            for f, (kind, i) in enumerate(terms):
                if kind == "sign":
                    theta[:, f] = np.where(np.abs(v[:, i]) < AT_REST * top, 0.0, theta[:, f])
            rows.append((theta, a))
        if not rows:
            raise ValueError("no piece between the events is long enough to fit")
        return np.concatenate([r[0] for r in rows]), np.concatenate([r[1] for r in rows])

    def fit(self, terms: list[Term], xi: Array, dt_max: float, states=None):
        """``(xi, states, rms)`` of ``shoot`` over the pieces, from ``xi`` [n, F] (its non-zeros fitted)
        and the pieces' ``states`` (from their smoothed derivatives unless given)."""
        pieces = []
        for k, (start, end, smooth) in enumerate(self.pieces):
            t, q = self.t[start:end], self.q[start:end]
            if states is not None:
                q0, v0 = states[k]
            elif smooth is not None:
                q0, v0 = smooth[0][0], smooth[1][0]
            else:
                q0, v0 = q[0], (q[1] - q[0]) / (t[1] - t[0])
            pieces.append((t, q, q0, v0))
        return shoot(terms, xi, xi != 0, pieces, dt_max)

    def rollout(self, terms: list[Term], xi: Array, state: tuple[Array, Array], times: Array, dt_max: float):
        """``(q, v)`` [T, n] at ``times`` from the last piece's fitted ``state``, bouncing on the contacts."""
        start = self.t[self.pieces[-1][0]]
        path, speed = integrate(
            terms, xi[None], state[0][None], state[1][None], times - start, dt_max, self.contacts
        )
        return path[0], speed[0]


class TermSets:
    """The shooting fits of sets of terms over a path's pieces, each set fitted once."""

    def __init__(self, path: PathPieces, terms: list[Term], dt_max: float):
        self.path, self.terms, self.dt_max, self.done = path, terms, dt_max, {}
        self.theta, self.target = path.regression(terms)
        self.kept = independent_terms(self.theta)
        self.scale = np.sqrt(np.mean(self.theta**2, 0))
        self.target_scale = np.sqrt(np.mean(self.target**2, 0)) + 1e-300

    def __call__(self, active: Array, start=None):
        """``(xi, states, rms)`` of the terms ``active`` [n, F] bool, shot from ``start`` (a fit of more
        terms) or from least squares on the smoothed derivatives."""
        key = active.tobytes()
        if key not in self.done:
            if start is not None:
                xi, states = np.where(active, start[0], 0.0), start[1]
            else:
                xi, states = np.zeros(active.shape), None
                for i in range(len(active)):
                    if active[i].any():
                        xi[i, active[i]] = np.linalg.lstsq(
                            self.theta[:, active[i]], self.target[:, i], rcond=None
                        )[0]
            xi[active & (xi == 0)] = 1e-12  # (an exact zero would leave the fitted terms)
            self.done[key] = self.path.fit(self.terms, xi, self.dt_max, states)
        return self.done[key]

    def small_sets(self, size: int, count: int) -> list[Array]:
        """Of each number of terms up to ``size``, the ``count`` sets [1, F] bool of one coordinate's
        linearly independent terms whose least-squares fit to the smoothed accelerations leaves the
        smallest residual. Terms that are one another over the fitted span (``1`` and ``sign q'`` of
        a part that has not stopped yet) each get their own set: the held-out end tells them apart."""
        sets = []
        for k in range(1, size + 1):
            ranked = []
            for chosen in itertools.combinations(range(len(self.terms)), k):
                theta = self.theta[:, list(chosen)]
                if np.linalg.matrix_rank(theta) < k:  # (terms the one can stand for the other: 1, sign q')
                    continue
                coef = np.linalg.lstsq(theta, self.target[:, 0], rcond=None)[0]
                ranked.append((float(np.sum((theta @ coef - self.target[:, 0]) ** 2)), chosen))
            for _, chosen in sorted(ranked)[:count]:
                active = np.zeros((1, len(self.terms)), dtype=bool)
                active[0, list(chosen)] = True
                sets.append(active)
        return sets

    def _weakest(self, active: Array, significance: Array, significant: float) -> tuple[int, int]:
        """The term to drop next: of the active terms [n, F] not ``significant``, the most complex kind
        (latest in ``TERM_KINDS``), else the least significant."""
        complexity = np.array([TERM_KINDS.index(kind) for kind, _ in self.terms], dtype=float)
        significance = np.nan_to_num(significance, nan=0.0, posinf=np.finfo(float).max)
        doubtful = active & (significance < significant)
        chosen = doubtful if doubtful.any() else active
        rank = np.broadcast_to(complexity, active.shape) if doubtful.any() else np.zeros(active.shape)
        rank = rank - significance / (significant + 1.0)  # (only the active terms are candidates)
        candidates = np.argwhere(chosen)
        return tuple(candidates[np.argmax(rank[chosen])])

    def backward(self, threshold: float, growth: float, significant: float = 25.0, kinds=None):
        """The nested sets of terms ``[(active, dropped, (xi, states, rms, significance))]``: from those
        PySINDy's ``STLSQ`` keeps at ``threshold`` (the smallest RMS share of a coordinate's acceleration
        a term may explain) on the smoothed derivatives, each next one without its least significant
        shot coefficient (``dropped``: that term's name), refitted, until the residual grows past
        ``growth`` times the first's; among the terms below ``significant`` (a Wald statistic: 25 is
        five standard deviations) the most complex kind goes first. One term at a time by
        significance, not all below a threshold at once: terms that the samples can barely tell apart
        (``q'``, ``sign q'`` and ``q'|q'|`` over a short span) trade their coefficients, so their large
        shares say nothing; their significance is low, the simplest of them stays, and the refit after
        each drop hands it the share of those dropped."""
        active = np.zeros((len(self.target_scale), len(self.terms)), dtype=bool)
        kept = self.kept & np.array([kinds is None or kind in kinds for kind, _ in self.terms])
        active[:, kept] = stlsq(self.theta[:, kept], self.target, threshold) != 0
        fit, dropped = self(active), ""
        floor = growth * fit[2] + 1e-6 * float(np.ptp(self.path.q))
        found = []
        while active.any():
            found.append((active, dropped, fit))
            weakest = self._weakest(active, fit[3], significant)
            active = active.copy()
            active[weakest] = False
            dropped = f"{term_name(self.terms[weakest[1]])} in q{weakest[0]}''"
            if not active.any():
                break
            fit = self(active, fit)
            if not fit[2] <= floor:
                break
        return found
