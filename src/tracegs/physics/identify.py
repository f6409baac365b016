"""One identified motion model per rigid part: how its generalised coordinates ``q`` [n] (a hinge's
or a rail's one, a chain's joint angles, a free body's position) evolve, ``q'' = f(q, q')``, identified
from their sampled path over the observed span.

``f`` is a sparse combination of library terms (``physics/sindy.py``): a constant (gravity, a
constant force), ``q`` and ``q'`` (springs, damping, and the coupling of the coordinates: two masses on
springs, or a chain of hinges at small angles, are one linear system), ``sin q`` and ``cos q`` of the
angular coordinates (a pendulum), ``sign q'`` (Coulomb friction) and ``q'|q'|`` (drag). The path is
split at its velocity jumps (``physics/events.py``: an impact, a bounce); one law holds on every piece,
each piece with its own state, and the jumps that reverse a velocity become contacts the model
bounces on with their restitution. The model continues from the state after the last event.

Selection is as for every law of the project: the model is fitted without the last
``holdout_fraction`` of the samples (the held-out end), from the terms that sparse regression keeps
down to one term by dropping the least significant (``TermSets.backward``) and, of one coordinate, from
the small sets that best fit its smoothed accelerations (``TermSets.small_sets``: over a short span
``q``, ``sin q``, ``cos q`` and the constant trade places, and dropping one at a time can follow the
wrong one), each set of terms scored by its rollout over the held-out end, and the sparsest set
within ``tie`` of the best (then the one of the simplest kinds) wins; its
constants are then refitted on the whole span. It is *adopted* only when
its held-out error is below ``margin`` times the baseline's (the learned physics' prediction of the
held-out end, passed in; moving on at the last velocity when none is) and its residual over the whole
fitted span is at most ``consistency`` of the path's motion; otherwise the result says which test
failed, and the caller keeps its baseline.

Why sparse regression over a library, not a neural ODE: the constants are the physics (a stiffness, a
restitution, g) and read as such in the report; a part's path is a few dozen samples, which fix a
handful of coefficients but not a network; the fit is linear least squares and a small shooting
problem, seconds on a CPU; and a term the library lacks shows as a failed held-out test, not as a
model that fits the span and drifts after it.

n: coordinates, F: library terms, T: samples, H: held-out samples. numpy float64.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .events import Event, detect_events
from .sindy import TERM_KINDS, Contact, Term, equation, evaluate, integrate, library_terms, term_name
from .term_sets import LIBRARIES, MIN_PIECE, MIN_REGRESSION, SMALL_SETS, SMALL_SHOTS, PathPieces, TermSets

Array = np.ndarray


def holdout_split(n_samples: int, holdout_fraction: float = 0.25) -> int:
    """How many of the first samples are fitted; the rest (a ``holdout_fraction``, at least one) are the
    held-out end, the rows of the baseline ``identify`` takes."""
    held = max(1, round(holdout_fraction * n_samples))
    if n_samples - held < MIN_REGRESSION + MIN_PIECE:
        raise ValueError(f"{n_samples} samples are too few to hold out {held} and fit the rest")
    return n_samples - held


@dataclass
class IdentifiedModel:
    """An identified model ``q'' = coefficients @ terms(q, q')`` with its contacts, its state at the end
    of the observed span, and the verdict of its selection."""

    terms: list[Term]
    coefficients: Array
    """[n, F] each coordinate's coefficient of each term."""
    angular: tuple[bool, ...]
    t_end: float
    q_end: Array
    """[n] the fitted trajectory's state at ``t_end``, the last sample (after the last event)."""
    v_end: Array
    contacts: tuple[Contact, ...] = ()
    events: tuple[Event, ...] = ()
    threshold: float = 0.0
    held_out: dict = field(default_factory=dict)
    """``{"samples", "model", "baseline"}``: RMS errors on the held-out end."""
    residual: float = math.inf
    """RMS residual over the fitted span relative to the path's motion (RMS about its mean)."""
    adopted: bool = False
    why: str = ""
    dt_max: float = 0.0
    """Largest integration step."""
    tried: list = field(default_factory=list)
    """``[{"threshold", "terms", "held_out"}]``: each distinct set of terms and its held-out error."""
    held_out_path: Array | None = field(default=None, repr=False, compare=False)
    """[H, n] the chosen terms, fitted without the held-out end, rolled out over it (not saved)."""

    @property
    def equations(self) -> list[str]:
        """Each coordinate's equation, e.g. ``q0'' = -9.81 - 0.31 q0'``."""
        return [equation(i, self.terms, row) for i, row in enumerate(self.coefficients)]

    def acceleration(self, q, v) -> Array:
        """[..., n] ``q''`` at the states ``q``, ``v`` [..., n]."""
        return evaluate(self.terms, np.asarray(q, float), np.asarray(v, float)) @ self.coefficients.T

    def linearised(self, q=None, eps: float = 1e-6) -> tuple[Array, Array]:
        """``(K, C)`` [n, n]: ``d q'' / d q`` and ``d q'' / d q'`` at rest at ``q`` (zeros unless given),
        the stiffness and damping matrices of the linearised system (central differences; ``sign q'``
        left out: it has no derivative at rest)."""
        n = len(self.coefficients)
        smooth = self.coefficients * np.array([kind != "sign" for kind, _ in self.terms])
        x, zero, step = np.zeros(n) if q is None else np.asarray(q, float), np.zeros((n, n)), eps * np.eye(n)

        def f(q, v):
            return evaluate(self.terms, q, v) @ smooth.T

        k = (f(x + step, zero) - f(x - step, zero)) / (2 * eps)
        c = (f(x + zero, step) - f(x + zero, -step)) / (2 * eps)
        return k.T, c.T

    @property
    def active_kinds(self) -> set[str]:
        """The kinds of the terms with a non-zero coefficient (``TERM_KINDS``)."""
        return {
            kind for (kind, _), used in zip(self.terms, (self.coefficients != 0).any(0), strict=True) if used
        }

    def growth_rate(self, q=None) -> float:
        """The largest real part of the eigenvalues of the system linearised at rest at ``q``
        (``linearised``): how fast, in e-folds per unit time, a small departure grows (> 0: an
        unstable model, a negative stiffness or damping; a passive joint's is <= 0)."""
        k, c = self.linearised(q)
        n = len(k)
        state = np.block([[np.zeros((n, n)), np.eye(n)], [k, c]])
        return float(np.linalg.eigvals(state).real.max())

    def rollout(self, t, q=None, v=None, t_start: float | None = None) -> tuple[Array, Array]:
        """``(q, v)`` [T, n] at the increasing times ``t`` [T] (>= the start) of the state ``q``, ``v`` [n]
        at ``t_start`` (the state at the end of the observed span unless given), by RK4 steps of at
        most ``dt_max``, bouncing on the contacts."""
        t = np.asarray(t, dtype=np.float64).reshape(-1)
        t_start = self.t_end if t_start is None else float(t_start)
        q = self.q_end if q is None else np.asarray(q, float)
        v = self.v_end if v is None else np.asarray(v, float)
        if len(t) and (t.min() < t_start - 1e-12 or np.any(np.diff(t) < 0)):
            raise ValueError(f"rollout times must increase from the start {t_start}")
        path, speed = integrate(
            self.terms, self.coefficients[None], q[None], v[None], t - t_start, self.dt_max, self.contacts
        )
        return path[0], speed[0]

    def report(self) -> dict:
        """What a run's summary says of the model: its equations, its non-zero constants by equation
        and term (``{"q0'' <- sin q0": -37.2}``), the times of its events, its held-out errors against
        the baseline's, its residual over the path, the sets of terms tried and the verdict (plain
        data, as ``to_dict``)."""
        return _plain(
            {
                "model": self.equations,
                "constants": {
                    f"q{i}'' <- {term_name(term)}": _finite(float(c))
                    for i, row in enumerate(self.coefficients)
                    for term, c in zip(self.terms, row, strict=True)
                    if c != 0
                },
                "events": [round(e.time, 6) for e in self.events],
                "held_out": {k: _finite(v) for k, v in self.held_out.items() if k != "samples"},
                "held_out_frames": self.held_out.get("samples"),
                "residual_of_path": _finite(self.residual),
                "tried": self.tried,
                "verdict": self.why,
            }
        )

    def to_dict(self) -> dict:
        """The model as plain JSON-able values (``from_dict`` reads it back): numbers, strings, lists and
        dicts only (no NumPy scalar), as ``torch.load(weights_only=True)`` reads a run's state."""
        return _plain(
            {
                "equations": self.equations,
                "terms": [[kind, i] for kind, i in self.terms],
                "coefficients": self.coefficients.tolist(),
                "angular": list(self.angular),
                "t_end": self.t_end,
                "q_end": self.q_end.tolist(),
                "v_end": self.v_end.tolist(),
                "contacts": [vars(c) for c in self.contacts],
                "events": [e.to_dict() for e in self.events],
                "threshold": self.threshold,
                "held_out": dict(self.held_out),
                "residual": _finite(self.residual),
                "adopted": self.adopted,
                "why": self.why,
                "dt_max": self.dt_max,
                "tried": list(self.tried),
            }
        )

    @classmethod
    def from_dict(cls, d: dict) -> IdentifiedModel:
        return cls(
            [(str(kind), int(i)) for kind, i in d["terms"]],
            np.asarray(d["coefficients"], dtype=np.float64).reshape(len(d["q_end"]), len(d["terms"])),
            tuple(bool(a) for a in d["angular"]),
            float(d["t_end"]),
            np.asarray(d["q_end"], dtype=np.float64),
            np.asarray(d["v_end"], dtype=np.float64),
            tuple(Contact(**c) for c in d["contacts"]),
            tuple(Event.from_dict(e) for e in d["events"]),
            float(d["threshold"]),
            dict(d["held_out"]),
            math.inf if d["residual"] is None else float(d["residual"]),
            bool(d["adopted"]),
            str(d["why"]),
            float(d["dt_max"]),
            list(d["tried"]),
        )


def _plain(value):
    """``value`` with every NumPy scalar in its dicts, lists and tuples made a Python number."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value.item() if isinstance(value, np.generic) else value


def _finite(x: float | None) -> float | None:
    return float(x) if x is not None and math.isfinite(x) else None


def _rms(a: Array, b: Array) -> float:
    error = float(np.sqrt(np.mean((a - b) ** 2)))
    return error if math.isfinite(error) else math.inf


def hold_velocity(t: Array, q: Array, n_fit: int, samples: int = 4) -> Array:
    """[H, n] no physics' prediction of the held-out end: moving on at the last velocity, a line fitted
    to the last ``samples`` fitted samples."""
    k = min(samples, n_fit)
    coef = np.polyfit(t[n_fit - k : n_fit], q[n_fit - k : n_fit], 1)
    return t[n_fit:, None] * coef[0] + coef[1]


def identify(
    t,
    q,
    baseline=None,
    angular=None,
    holdout_fraction: float = 0.25,
    margin: float = 0.8,
    consistency: float = 0.05,
    tie: float = 0.05,
    threshold: float = 1e-3,
    growth: float = 20.0,
    friction: bool = True,
    drag: bool = True,
    detect: bool = True,
) -> IdentifiedModel:
    """The model of the path ``q`` [T, n] (or [T]) at the increasing times ``t`` [T] (module
    docstring). ``baseline`` [H, n]: the prediction to beat on the held-out end (its rows the samples
    from ``holdout_split(T, holdout_fraction)`` on); ``angular`` [n]: which coordinates are angles (none
    unless given); ``detect``: split the path at its velocity jumps."""
    t = np.asarray(t, dtype=np.float64).reshape(-1)
    q = np.asarray(q, dtype=np.float64).reshape(len(t), -1)
    n = q.shape[1]
    if np.any(np.diff(t) <= 0) or not np.isfinite(q).all():
        raise ValueError("the path's times must increase and its samples be finite")
    n_fit = holdout_split(len(t), holdout_fraction)
    angular = tuple(bool(a) for a in angular) if angular is not None else (False,) * n
    baseline = hold_velocity(t, q, n_fit) if baseline is None else np.asarray(baseline, float).reshape(-1, n)
    if len(baseline) != len(t) - n_fit:
        raise ValueError(f"the baseline has {len(baseline)} rows, the held-out end {len(t) - n_fit}")
    terms = library_terms(n, angular, friction, drag)
    events = detect_events(t, q) if detect else []
    dt_max = 0.5 * float(np.min(np.diff(t)))
    empty = IdentifiedModel(terms, np.zeros((n, len(terms))), angular, float(t[-1]), q[-1], 0 * q[-1])
    empty.events, empty.dt_max = tuple(events), dt_max
    held = PathPieces(t, q, events, n_fit)
    if all(s is None for _, _, s in held.pieces):
        return _verdict(empty, False, "too few samples between the velocity jumps to fit a model")

    # the nested sets of terms on the fitted samples, each scored on the held-out end
    baseline_rms, scored = _rms(baseline, q[n_fit:]), []
    fits = TermSets(held, terms, dt_max)
    candidates = [
        (active, dropped, fit[:2])
        for kinds in LIBRARIES
        for active, dropped, fit in fits.backward(threshold, growth, kinds=kinds)
    ]
    if n == 1:  # small sets too: over a short span terms trade places (q, sin q, cos q, 1 near rest)
        seen = {active.tobytes() for active, *_ in candidates}
        for active in fits.small_sets(SMALL_SETS, SMALL_SHOTS):
            if active.tobytes() not in seen:
                candidates.append((active, "", fits(active)[:2]))
    for active, dropped, (xi, states) in candidates:
        prediction = held.rollout(terms, xi, states[-1], t[n_fit:], dt_max)[0]
        scored.append((active, dropped, int(active.sum()), _rms(prediction, q[n_fit:]), prediction))
    tried = [{"dropped": d, "terms": k, "held_out": _finite(e)} for _, d, k, e, _ in scored]
    if not scored:
        return _verdict(empty, False, "the regression kept no term")
    best = min(v[3] for v in scored)
    good = best * (1 + tie) + 1e-6 * float(np.ptp(q))
    complexity = np.array([TERM_KINDS.index(kind) for kind, _ in terms])
    active, _, _, error, prediction = min(  # the fewest terms, then the simplest kinds, then the error
        (v for v in scored if v[3] <= good), key=lambda v: (v[2], int(complexity @ v[0].sum(0)), v[3])
    )

    # the chosen terms refitted on the whole span
    whole = PathPieces(t, q, events, len(t))
    xi, states, rms, _ = TermSets(whole, terms, dt_max)(active)
    fitted = np.concatenate([np.arange(a, b) for a, b, _ in whole.pieces])
    motion = float(np.sqrt(np.mean((q[fitted] - q[fitted].mean(0)) ** 2))) + 1e-300
    end_q, end_v = whole.rollout(terms, xi, states[-1], t[-1:], dt_max)
    model = IdentifiedModel(
        terms, xi, angular, float(t[-1]), end_q[-1], end_v[-1], whole.contacts, tuple(events), threshold
    )
    model.held_out = {"samples": len(t) - n_fit, "model": _finite(error), "baseline": _finite(baseline_rms)}
    model.residual, model.dt_max, model.tried = rms / motion, dt_max, tried
    model.held_out_path = prediction
    if not math.isfinite(error) or not np.isfinite(xi).all():
        return _verdict(model, False, "its rollout over the held-out end blows up")
    if not error < margin * baseline_rms:
        why = f"its held-out error {error:.3g} is not below {margin} times the baseline's {baseline_rms:.3g}"
        return _verdict(model, False, why)
    if not model.residual <= consistency:
        why = f"its residual over the fitted span is {model.residual:.3g} of the path's motion (over {consistency})"
        return _verdict(model, False, why)
    return _verdict(model, True, f"held-out error {error:.3g} against the baseline's {baseline_rms:.3g}")


def _verdict(model: IdentifiedModel, adopted: bool, why: str) -> IdentifiedModel:
    model.adopted, model.why = adopted, ("adopted: " if adopted else "not adopted: ") + why
    return model
