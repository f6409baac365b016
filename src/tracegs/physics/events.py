"""Contacts as events: the velocity jumps of a sampled path ``q(t_k)`` (an impact, a bounce), where it
is split so that a smooth model is fitted on either side (``physics/identify.py``).

Between samples a smooth path changes its velocity by about ``q'' dt``, and that change itself varies
slowly; an impact changes it at once, within a frame. The change of the finite-difference velocity at
each sample, less its running median over the neighbouring samples, is that surprise; a sample whose
surprise stands out from the path's own (``threshold`` times its median absolute deviation) and from
its speed (``min_jump`` of its largest finite-difference speed) marks an event, adjacent ones one
event. The positions on both sides are good (only the velocity jumps), so the event's time is where a
quadratic through the samples before it meets one through the samples after it, and the velocities
before and after are theirs there: exact on a path that is piecewise quadratic (a ball under gravity),
and with the restitution ``e = -v_after / v_before`` of every velocity component that the jump
reverses.

n: coordinates, T: samples. numpy float64.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import median_filter

from .sindy import Contact

Array = np.ndarray

WINDOW = 6
"""Samples on each side of an event that its local quadratics are fitted to (fewer where a segment is
shorter)."""


@dataclass(frozen=True)
class Event:
    """A velocity jump between the samples ``before`` and ``after`` (equal when it is at a sample)."""

    time: float
    before: int
    after: int
    position: tuple[float, ...]
    """[n] ``q`` at the event."""
    v_before: tuple[float, ...]
    v_after: tuple[float, ...]
    restitution: tuple[float | None, ...]
    """[n] ``e = -v_after / v_before`` of the components the jump reverses, ``None`` elsewhere."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> Event:
        return cls(
            float(d["time"]),
            int(d["before"]),
            int(d["after"]),
            *(tuple(d[k]) for k in ("position", "v_before", "v_after", "restitution")),
        )


def _quadratic(t: Array, q: Array, t_ref: float) -> Array:
    """[3, n] the polynomial (coefficients of ``(t - t_ref)^2, (t - t_ref), 1``) of degree at most 2
    (fewer samples: lower) through ``q`` [T, n] at ``t`` [T] by least squares."""
    degree = min(2, len(t) - 1)
    coef = np.polyfit(t - t_ref, q, degree)
    return np.vstack([np.zeros((2 - degree, q.shape[1])), coef.reshape(degree + 1, -1)])


def _value(coef: Array, s: float) -> tuple[Array, Array]:
    """``(q, q')`` [n] of the quadratics ``coef`` [3, n] at ``s`` (relative to their ``t_ref``)."""
    return coef[0] * s**2 + coef[1] * s + coef[2], 2 * coef[0] * s + coef[1]


def jump_samples(t: Array, q: Array, threshold: float = 8.0, min_jump: float = 0.2) -> Array:
    """[T] bool: the samples where the velocity of ``q`` [T, n] at the times ``t`` [T] jumps (module
    docstring)."""
    flagged = np.zeros(len(t), dtype=bool)
    if len(t) < 5:
        return flagged
    u = np.diff(q, axis=0) / np.diff(t)[:, None]  # [T-1, n] the velocities between samples
    change = np.diff(u, axis=0)  # [T-2, n] at the samples 1..T-2
    surprise = change - median_filter(change, size=(5, 1), mode="nearest")
    deviation = np.median(np.abs(surprise - np.median(surprise, 0)), 0) * 1.4826
    bound = np.maximum(threshold * deviation, min_jump * np.abs(u).max(0)) + 1e-12
    flagged[1:-1] = (np.abs(surprise) > bound).any(1)
    return flagged


def _event(t: Array, q: Array, first: int, last: int, lo: int, hi: int) -> Event:
    """The event flagged from sample ``first`` to ``last``, its quadratics fitted to the samples
    ``lo..first`` and ``last..hi - 1``."""
    before = slice(max(lo, first - WINDOW + 1), first + 1)
    after = slice(last, min(hi, last + WINDOW))
    t_ref = float(t[first])
    pre, post = _quadratic(t[before], q[before], t_ref), _quadratic(t[after], q[after], t_ref)
    jump = np.abs(_value(post, 0.0)[1] - _value(pre, 0.0)[1]) / (np.abs(np.diff(q, axis=0)).max(0) + 1e-300)
    i = int(np.argmax(jump))  # the coordinate that jumps most times the event
    gap = pre[:, i] - post[:, i]  # where the two quadratics meet in [t_first - dt, t_last + dt]
    span = (float(t[max(first - 1, 0)] - t_ref), float(t[min(last + 1, len(t) - 1)] - t_ref))
    roots = [r.real for r in np.roots(np.trim_zeros(gap, "f")) if abs(r.imag) < 1e-9] if gap.any() else []
    inside = [r for r in roots if span[0] <= r <= span[1]]
    middle = 0.5 * float(t[last] - t_ref)
    s = min(inside, key=lambda r: abs(r - middle)) if inside else middle
    position, v_before = _value(pre, s)
    v_after = _value(post, s)[1]
    speed = np.abs(v_before).max() + 1e-300
    restitution = tuple(
        float(-a / b) if b * a < 0 and abs(b) > 0.1 * speed else None
        for a, b in zip(v_after, v_before, strict=True)
    )
    return Event(
        t_ref + s,
        first,
        last,
        tuple(map(float, position)),
        tuple(map(float, v_before)),
        tuple(map(float, v_after)),
        restitution,
    )


def detect_events(t, q, threshold: float = 8.0, min_jump: float = 0.2) -> list[Event]:
    """The velocity jumps of the samples ``q`` [T, n] (or [T]) at the increasing times ``t`` [T], in
    time order (module docstring)."""
    t = np.asarray(t, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64).reshape(len(t), -1)
    flagged = jump_samples(t, q, threshold, min_jump)
    runs, k = [], 0
    while k < len(t):
        if flagged[k]:
            end = k
            while end + 1 < len(t) and flagged[end + 1]:
                end += 1
            runs.append((k, end))
            k = end + 1
        else:
            k += 1
    events = []
    for j, (first, last) in enumerate(runs):
        lo = runs[j - 1][1] if j else 0
        hi = runs[j + 1][0] + 1 if j + 1 < len(runs) else len(t)
        events.append(_event(t, q, first, last, lo, hi))
    return events


def segments(n_samples: int, events: list[Event]) -> list[tuple[int, int]]:
    """``[(start, stop)]``: the sample ranges between the events, the first from 0, the last to
    ``n_samples`` (each event's ``after`` sample starts the next)."""
    bounds = [0] + [e.after for e in events] + [n_samples]
    stops = [e.before + 1 for e in events] + [n_samples]
    return [(bounds[k], stops[k]) for k in range(len(bounds) - 1)]


def contacts_of(events: list[Event], q: Array) -> tuple[Contact, ...]:
    """The contacts the ``events`` that reverse a velocity component show: one per coordinate and
    direction, its position and restitution the mean of its events' within 5% of the coordinate's
    range of ``q`` [T, n] (a floor hit again); a far one is another contact."""
    found: list[list] = []
    for e in events:
        for i, r in enumerate(e.restitution):
            if r is None:
                continue
            d, x = int(np.sign(e.v_before[i])), e.position[i]
            near = 0.05 * (float(np.ptp(q[:, i])) + 1e-300)
            match = next(
                (c for c in found if c[0] == i and c[1] == d and abs(np.mean(c[2]) - x) <= near), None
            )
            if match is None:
                found.append([i, d, [x], [r]])
            else:
                match[2].append(x)
                match[3].append(r)
    return tuple(Contact(i, float(np.mean(x)), d, float(np.mean(r))) for i, d, x, r in found)
