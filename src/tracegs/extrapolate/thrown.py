"""Thrown parts that bounce (``extrapolation.joint_laws``): a part in flight that hits a floor within the
training span and flies on (a ball bouncing), which neither a free body (a parabola through the floor)
nor the learned physics (the last push held) predicts past its next contact.

The part's centre moves on a line plus a coordinate ``q`` along one direction ``n``, gravity's: the
centre's departure from its best straight line lies along ``n`` (its first principal direction). The
centre of a frame is the centroid of the solid its Gaussians bound (``centre_of_mass`` of their main
piece, as a free body's): a spinning ball's Gaussians slide over it, so its rigid fits from frame to
frame are poor, and their mean lies off the centre where the cameras saw one side more densely, an
offset that turns with the ball and bends the centre's path.
``q(t)`` follows the ``bounce`` law (``physics/force_law.py``: ``q'' = -g`` above a floor, the speed
reversed and scaled by the restitution ``e`` at a contact); the part spins at the constant angular
velocity of its rigid turns from frame to frame. As a joint law is, it is chosen by the held-out end of
the span (``joint_law_holdout``): fitted to the frames before it (which must show a contact, or the
floor is unknown), it must predict the part's positions there about as well as the learned physics
started at the same frame (within ``1 / joint_law_tolerance`` of its error). Not better: those frames
are a flight, which the learned physics holds too; the next contact, which it cannot hold, no frame
before the handover shows. No images.

M: a part's Gaussians, T: frames.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..physics.force_law_fit import FittedLaw, fit_law
from ..physics.free_body import centre_of_mass, fit_rigid_transform, main_piece
from ..physics.identify import IdentifiedModel
from ..physics.sindy import Contact
from ..physics.so3 import quat_to_axis_angle, rotmat_to_quat
from .joint_motion import rms_distance, thrown_motion

MIN_BOUNCES_FRAMES = 3
"""Fewest frames after the first contact (of those fitted) for the restitution to be identified."""
ONE_DIRECTION = 0.2
"""Largest ratio of the second to the first principal spread of the centre's departure from its line
for a fall along one direction (``bounce``'s ball: 0.03; a part going round a circle: about 1)."""
CONTACT_FRAMES = 3
"""Frames on each side of a contact that the law is refitted without (``refit_bounce``): f_defo, smooth
in time, rounds the kink of a bounce (``bounce``: its ball's centre stops 0.10 of a 0.45 drop above
the floor, and is within 0.03 of its path two frames away)."""


def _line(t: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(c0 [3], u [3])``: the least-squares line ``c0 + u t`` through the points ``c`` [T, 3]."""
    design = np.stack([np.ones_like(t), t], 1)
    coef = np.linalg.lstsq(design, c, rcond=None)[0]
    return coef[0], coef[1]


def centres(path: torch.Tensor) -> np.ndarray:
    """[T, 3] the centre of the points ``path`` [T, M, 3] in each frame: the centroid of the solid that
    the main piece of the last frame's points bounds (``physics.free_body``: ``main_piece``,
    ``centre_of_mass``)."""
    piece = main_piece(path[-1])
    return np.stack([centre_of_mass(p[piece]).numpy() for p in path])


def spin_rate(path: torch.Tensor, times: np.ndarray) -> torch.Tensor:
    """[3] the mean angular velocity of the rigid turns of the points ``path`` [T, M, 3] from each frame
    to the next (Kabsch about their means), world frame."""
    rates = []
    for k in range(len(times) - 1):
        a, b = path[k] - path[k].mean(0), path[k + 1] - path[k + 1].mean(0)
        turn, _ = fit_rigid_transform(a, b)
        rates.append(quat_to_axis_angle(rotmat_to_quat(turn)) / float(times[k + 1] - times[k]))
    return torch.stack(rates).mean(0) if rates else torch.zeros(3, dtype=torch.float64)


def _contacts(law: FittedLaw, t_end: float, samples: int = 2000) -> np.ndarray:
    """The times in (``law.t0``, ``t_end``] at which ``law`` (a ``bounce``) reverses a fall on its
    floor, to within ``(t_end - t0) / samples``."""
    dense = np.linspace(law.t0, t_end, samples + 1)
    v = law.state_at(dense)[1].numpy()
    return dense[1:][(v[:-1] < 0) & (v[1:] > v[:-1] + 0.5 * law.params[0] * (dense[1] - dense[0]))]


def first_contact(law: FittedLaw, t_end: float) -> float | None:
    """The first time in (``law.t0``, ``t_end``] at which ``law`` (a ``bounce``) puts ``q`` on its
    floor; None when it does not."""
    contacts = _contacts(law, t_end)
    return float(contacts[0]) if len(contacts) else None


def refit_bounce(t: np.ndarray, q: np.ndarray, law: FittedLaw) -> FittedLaw:
    """``law`` (a ``bounce`` fitted to ``q`` [T] at the times ``t`` [T]) fitted again without the
    ``CONTACT_FRAMES`` samples on each side of each of its contacts, which f_defo rounds: its start,
    gravity, restitution and floor by ``scipy.optimize.least_squares`` (twice: the contacts move with
    the fit)."""
    from scipy.optimize import least_squares

    from ..physics.force_law import LAWS, integrate

    step, dt_max = float(np.median(np.diff(t))), law.dt_max
    lower, upper = [-np.inf, -np.inf, 0.0, 0.0, -np.inf], [np.inf, np.inf, np.inf, 1.0, np.inf]
    for _ in range(2):
        contacts = _contacts(law, float(t[-1]))
        keep = np.all(np.abs(t[:, None] - contacts[None]) > CONTACT_FRAMES * step, axis=1)
        if not len(contacts) or int(keep.sum()) < 6:
            break
        s, target = t[keep] - t[0], q[keep]

        def residual(x: np.ndarray, s=s, target=target) -> np.ndarray:
            return integrate(LAWS["bounce"], x[None, 2:], [x[0]], [x[1]], s, dt_max)[0][0] - target

        start = np.clip([law.q0, law.v0, *law.params], lower, upper)
        x = least_squares(residual, start, bounds=(lower, upper), x_scale="jac").x
        rms = float(np.sqrt(np.mean(residual(x) ** 2)))
        params = tuple(float(v) for v in x[2:])
        law = FittedLaw("bounce", params, float(t[0]), float(x[0]), float(x[1]), rms, dt_max)
    return law


def fit_thrown(path: torch.Tensor, times: np.ndarray) -> dict | None:
    """The thrown part whose means are ``path`` [T, M, 3] at the increasing ``times`` [T]: ``{"axis"
    n [3], "velocity" u [3] (along the floor), "spin" w [3], "law" (a ``bounce`` ``FittedLaw`` of its
    centre's height ``q = c . n`` over the frames, ``refit_bounce``), "contact"`` (its first, or
    None), ``"centre"`` [3] (at the last frame), ``"centres"`` [T, 3] (``centres``)``}``; None when
    the centre moves on a straight line (no direction to bounce along) or bends in a plane
    (``ONE_DIRECTION``)."""
    c = centres(path)
    c0, u = _line(times, c)
    residual = c - c0 - times[:, None] * u
    scale = float(np.abs(c - c.mean(0)).max())
    if float(np.abs(residual).max()) <= 1e-6 * max(scale, 1e-12):
        return None
    _, spread, axes = np.linalg.svd(residual - residual.mean(0), full_matrices=False)
    if spread[1] > ONE_DIRECTION * spread[0]:  # it bends in a plane (a part going round): no fall
        return None
    n = axes[0]
    best = None
    for sign in (1.0, -1.0):  # gravity along -n: the law's g is >= 0, so try both senses of n
        q = c @ (sign * n)
        try:
            law = fit_law(times, q, "bounce")
        except (ValueError, np.linalg.LinAlgError):
            continue
        if math.isfinite(law.rms) and (best is None or law.rms < best[1].rms):
            best = (sign * n, law)
    if best is None:
        return None
    n, law = best
    law = refit_bounce(times, c @ n, law)
    _, u = _line(times, c - (c @ n)[:, None] * n)
    contact = first_contact(law, float(times[-1]))
    spin = spin_rate(path, times)
    return {
        "axis": n,
        "velocity": u,
        "spin": spin,
        "law": law,
        "contact": contact,
        "centre": torch.from_numpy(c[-1]),
        "centres": c,
    }


def _stored(fit: dict, t: float) -> dict:
    """The thrown part of ``fit`` (``fit_thrown``) as stored, from its state at ``t``, its last frame:
    its height's ``bounce`` law as the identified model it is (``physics/identify.py``: ``q'' = -g``,
    a contact on the floor with the restitution ``e``)."""
    law = fit["law"]
    q0, v0 = (float(x[0]) for x in law.state_at([t]))
    g, e, floor = (float(p) for p in law.params)
    model = IdentifiedModel(
        [("1", -1)],
        np.array([[-g]]),
        (False,),
        t,
        np.array([q0]),
        np.array([v0]),
        (Contact(0, floor, -1, e),),
        dt_max=law.dt_max,
        adopted=True,
    )
    return {
        "joint": "thrown",
        "axis": torch.from_numpy(fit["axis"]),
        "pivot": fit["centre"],
        "velocity": torch.from_numpy(fit["velocity"]),
        "spin": fit["spin"],
        "model": model.to_dict(),
        "parent": None,
    }


def _predict(fit: dict, start: torch.Tensor, t_start: float, times: np.ndarray) -> torch.Tensor:
    """[H, M, 3] the points ``start`` [M, 3] at ``t_start`` (``fit``'s last frame) moved by ``fit``
    (``fit_thrown``) to ``times``."""
    part = _stored(fit, t_start)
    moved = []
    for t in times:
        turn, shift = thrown_motion(part, t_start, float(t))
        moved.append(start @ turn.T + shift)
    return torch.stack(moved)


def choose_thrown(
    path: list[torch.Tensor], times: list[float], rows, learned, settings
) -> tuple[dict | None, dict]:
    """``(stored part or None, report)`` of the Gaussians ``rows`` on their ``path`` [T] x [M, 3] at the
    increasing ``times`` [T] (the handover last) as a thrown part (module docstring); ``learned`` the
    joint laws' ``_LearnedBacktest``."""
    from ..physics.force_law_fit import _split

    truth = torch.stack([p.detach().double().cpu() for p in path])
    t = np.asarray(times, dtype=np.float64)
    n = _split(t, t, settings.joint_law_holdout)
    entry: dict = {"gaussians": int(rows.sum()), "model": "thrown", "adopted": False}
    before = fit_thrown(truth[:n], t[:n])
    if (
        before is None
        or before["contact"] is None
        or int((t[:n] > before["contact"]).sum()) < MIN_BOUNCES_FRAMES
    ):
        return None, {
            **entry,
            "why": "no contact with a floor seen before the held-out frames: the learned physics",
        }
    law_means = _predict(before, truth[n - 1], float(t[n - 1]), t[n:])
    learned_means = learned.means(float(t[n - 1]), [float(s) for s in t[n:]])[:, rows.cpu()]
    whole = fit_thrown(truth, t)
    if whole is None or whole["contact"] is None:
        return None, {**entry, "why": "no contact with a floor seen: the learned physics"}
    law = whole["law"]
    entry.update(
        law=law.name,
        constants={k: float(v) for k, v in law.constants.items()},
        contact=whole["contact"],
        held_out_frames=len(t) - n,
        position_rms={
            "law": rms_distance(law_means, truth[n:]),
            "learned": rms_distance(learned_means, truth[n:]),
        },
    )
    g, e = law.params[0], law.params[1]
    if not (g > 0 and 0 < e < 1):
        return None, {**entry, "why": "not a fall with a lossy bounce: the learned physics"}
    x = truth[-1]
    radius = float((x - x.mean(0)).square().sum(-1).mean().sqrt())
    if float(np.ptp(whole["centres"] @ whole["axis"])) < radius:
        return None, {**entry, "why": "it rises and falls less than its size: the learned physics"}
    # the held-out frames are a flight, which the learned physics holds as well; what it cannot hold is
    # the next contact, which no frame before the handover shows: about as good there is enough
    if not entry["position_rms"]["law"] <= entry["position_rms"]["learned"] / settings.joint_law_tolerance:
        return None, {
            **entry,
            "why": "the learned physics predicts the held-out frames better: the learned physics",
        }
    return _stored(whole, float(t[-1])), {**entry, "adopted": True, "why": "adopted"}
