"""The rig of a trained run, for a simulator: its parts as rigid bodies on joints, each with the motion
model the run predicts it with, in the scene's world frame and time at the handover (``mjcf.py``,
``urdf.py``).

The parts are the run's own (its extrapolation state, ``tracegs calibrate``), so no segmentation is
needed: the still Gaussians are the world; each part with an identified model (``joint_laws``) is a
body on its joint, a hinge or a rail (a part carried by another is its child: a box on a turntable, a
chain's second link), a part on no joint (``"free"``: slides along the directions it moves in, and a
hinge it spins on) or a thrown part (a free joint over a floor); each free body a free joint. The
other moving groups keep the learned physics in the run, which has no simulator term: each is put
on the hinge or rail that carries its Gaussians along f_defo's path (``extrapolate.joints.fit_joint``),
moving on at its velocity there with its acceleration held (the learned physics' constant
accelerations), unless its rigid parts (``chain.split_parts``) turn on joints of their own; else
each of its rigid parts is, or moves as its learned physics does at the handover (``_twist_body``);
a free body that turns on a joint in a larger body's frame becomes its child (``_carried``). The
body's ``why`` says which and why.

Each body's shape is the convex hull of its Gaussians' means at the handover (simulators collide
convex shapes, and a part's Gaussians lie on its surface, which the hull closes), its mass and
inertia the hull's at ``DENSITY``.

N: Gaussians, M: a body's Gaussians, T: frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..extrapolate.chain import split_parts
from ..extrapolate.free_bodies import moving_groups
from ..extrapolate.joints import MIN_GAUSSIANS, fit_joint, fits_joint, frame_times, part_transforms
from ..physics.free_body import FreeBody, fit_rigid_velocity
from ..physics.identify import IdentifiedModel
from ..physics.integrate import particle_velocity

DENSITY = 1000.0
"""Mass per cubic scene unit of every body (water's, in kilograms, for a scene in metres). The
identified models fix accelerations, not masses: the exported forces are scaled by the bodies'
inertias, so any density gives the same motion."""
RAIL_TURN = 0.1
"""Smallest turn (radians) over the span of a hinge that a group on the learned physics is put on;
a straight motion is a turn about a far axis too, and a rail is what it is."""
DISTINCT_AXES = math.radians(10)
"""Smallest angle between the axes of two rigid parts of a group, each on a joint of its own, for the
group to be exported as those parts rather than on its one joint."""
TWIST_RESIDUAL = 0.5
"""Largest RMS residual of a group's best rigid velocity field, relative to its RMS speed, for the
learned physics to move it as one body."""
AXLE = 0.5
"""Farthest a twist's axis may pass from a group's centre, relative to its RMS radius, for it to be
a hinge (a wheel turning on its axle); farther (a ball rolling about its contact, a disc sliding while
it spins) it is a free body."""
TWIST_INLIERS = 0.8
"""Share of a group's Gaussians whose velocities its twist is refitted to."""
SCREW = 0.2
"""A twist whose turn carries its points (turn x radius) faster than this fraction of its centre's
speed turns (a hinge where the axis passes through the part and the motion along it is below this
fraction); one whose turn is slower than this fraction of its speed is a translation (a rail)."""
LAST_FRAMES = 5
"""The last frames of a part's coordinate whose quadratic gives its velocity and held acceleration at
the handover (a part on the learned physics)."""


@dataclass
class Body:
    """One rigid part: its Gaussians ``rows`` [N] bool and its joint in the world frame at the handover
    (``joint``: ``"hinge"``, ``"slide"``, ``"planar"`` (slides along ``basis`` [k, 3] and a hinge about
    ``axis`` through ``pivot``), ``"free"`` or ``"fixed"``; ``parent``: the index of the body that
    carries it, None for the world), the model of its coordinates (``model``, in the joint's own
    coordinate, the planar part's along ``basis``) and its state at the handover."""

    name: str
    rows: torch.Tensor
    joint: str
    axis: np.ndarray
    pivot: np.ndarray
    parent: int | None = None
    basis: np.ndarray | None = None
    model: IdentifiedModel | None = None
    coordinate: int = 0
    """Which of ``model``'s coordinates is the joint's (a chain's link)."""
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """The joint's velocity at the handover: [1] a hinge's or a rail's, [k + 1] a planar part's (its
    slides, then its spin), [6] a free body's (its centre of mass's velocity, then its angular
    velocity, world frame)."""
    acceleration: np.ndarray | None = None
    """[3] a free body's acceleration (gravity's where it falls); None: none."""
    floor: dict | None = None
    """A thrown part's floor: ``{"normal" [3], "offset"`` (the plane ``normal . x = offset``)
    ``, "restitution", "radius"}`` (the part hits it as a ball of that radius about its centre, where its
    model's contact puts it: its hull, a spinning ball's Gaussians' hull, is no sphere)."""
    source: str = "identified model"
    why: str = ""
    left_out: list[str] = field(default_factory=list)
    """What of the run's motion of it the joint cannot do."""
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """[M, 3] its Gaussians' means at the handover: its hull (``hull``)."""


@dataclass
class Rig:
    """The world (the Gaussians of no body) and the bodies at the handover ``t0``."""

    t0: float
    bodies: list[Body]
    up: np.ndarray
    """[3] the scene's up (the cameras' mean up): gravity's direction is down."""


def _rms_radius(points: np.ndarray, centre: np.ndarray) -> float:
    """The RMS distance of ``points`` [M, 3] from ``centre`` [3] (0 for none)."""
    return float(np.sqrt(((points - centre) ** 2).sum(1).mean())) if len(points) else 0.0


def _np(x) -> np.ndarray:
    return np.asarray(torch.as_tensor(x).detach().double().cpu().numpy(), dtype=np.float64)


def _joint_kind(part: dict) -> str:
    return {"slider": "slide", "hinge": "hinge", "free": "planar", "thrown": "free"}[part["joint"]]


def _from_part(k: int, part: dict, rows: torch.Tensor, points: np.ndarray) -> Body:
    """The body of the stored joint part ``k`` (``extrapolate/joints.py``)."""
    model = IdentifiedModel.from_dict(part["model"])
    kind, name = _joint_kind(part), f"part{k + 1}"
    common = {"rows": rows, "points": points, "model": model, "name": name}
    if kind in ("hinge", "slide"):
        c = part.get("coordinate", 0)
        return Body(
            joint=kind, axis=_np(part["axis"]), pivot=_np(part["pivot"]), parent=part.get("parent"),
            coordinate=c, velocity=np.array([model.v_end[c]]), why="its identified model", **common,
        )  # fmt: skip
    turn = _np(part["spin"])
    if kind == "planar" and len(part["basis"]) == 1:  # its centre moves along one line: a rail
        spin = float(np.linalg.norm(turn))
        return Body(
            joint="slide", axis=_np(part["basis"])[0], pivot=np.zeros(3), velocity=np.array([model.v_end[0]]),
            why="its identified model (its centre moves along one line)",
            left_out=[f"its spin of {spin:.3g} rad per unit time (a rail does not turn)"] if spin > 0 else [],
            **common,
        )  # fmt: skip
    if kind == "planar":
        rate = float(np.linalg.norm(turn))  # it spins about its spin, else across its plane of motion
        axis = turn if rate > 0 else np.cross(*_np(part["basis"])[:2])
        return Body(
            joint="planar", axis=axis / np.linalg.norm(axis), pivot=_np(part["pivot"]),
            basis=_np(part["basis"]), velocity=np.concatenate([model.v_end, [rate]]),
            why="its identified model (centre along its axes; spins on)", **common,
        )  # fmt: skip
    up, contact = _np(part["axis"]), model.contacts[0] if model.contacts else None
    centre = _np(part["pivot"])
    velocity = _np(part["velocity"]) + up * float(model.v_end[0])
    floor = None
    if contact is not None:  # the centre stops at ``contact.position`` along ``up``: a ball's radius above it
        radius = _rms_radius(points, centre)
        offset = contact.position - radius + (float(centre @ up) - float(model.q_end[0]))
        floor = {"normal": up, "offset": offset, "restitution": contact.restitution, "radius": radius}
    return Body(
        joint="free", axis=up, pivot=centre, velocity=np.concatenate([velocity, turn]),
        acceleration=up * float(model.coefficients[0, 0]), floor=floor, why="thrown: its identified model",
        **common,
    )  # fmt: skip


def _from_free_body(k: int, row: torch.Tensor, rows: torch.Tensor, points: np.ndarray) -> Body:
    body = FreeBody.from_tensor(row)
    c0 = _np(body.c0 + body.shift)
    return Body(
        name=f"body{k + 1}", rows=rows, joint="free", axis=np.zeros(3), pivot=c0,
        velocity=np.concatenate([_np(body.v), _np(body.w)]), acceleration=_np(body.a),
        source="free body", why="a free body", points=points,
    )  # fmt: skip


def _held(times: np.ndarray, q: np.ndarray) -> tuple[float, float]:
    """``(velocity, acceleration)`` at the last of ``times`` of the quadratic through the last
    ``LAST_FRAMES`` samples of ``q``."""
    t, y = times[-LAST_FRAMES:] - times[-1], q[-LAST_FRAMES:]
    c = np.polyfit(t, y, 2) if len(t) >= 3 else np.array([0.0, *np.polyfit(t, y, 1)])
    return float(c[1]), float(2 * c[0])


def _on_joint(name: str, rows, x0: torch.Tensor, path: list[torch.Tensor], times, settings) -> tuple:
    """``(body or None, rigid residual, the joint's residual)``: a moving group on the learned physics on the hinge or rail
    that carries it along its ``path`` (f_defo's; ``fit_joint``, as a joint part's; a hinge that turns
    less than ``RAIL_TURN`` is a rail), moving on at its velocity there with its acceleration held;
    None where none does."""
    joint, q, residuals = fit_joint(x0, path, RAIL_TURN)
    if joint is None or not fits_joint(joint, residuals, settings):
        return None, residuals["rigid"], math.inf
    q = _np(q)
    v, a = _held(times, q)
    model = IdentifiedModel(
        [("1", -1)], np.array([[a]]), (joint["joint"] == "hinge",), float(times[-1]), np.array([q[-1]]),
        np.array([v]),
    )  # fmt: skip
    body = Body(
        name=name, rows=rows, joint=_joint_kind(joint), axis=_np(joint["axis"]), pivot=_np(joint["pivot"]),
        model=model, velocity=np.array([v]), source="learned physics", points=_np(x0),
        why="the learned physics (no model adopted): on the joint that carries it, moving on at its "
        "velocity with its acceleration held",
    )  # fmt: skip
    return body, residuals["rigid"], residuals[joint["joint"]]


def _twist_body(name: str, rows, points: np.ndarray, twist: tuple, rigid: float) -> Body:
    """A moving group that no joint carries along f_defo's path (its Gaussians slide over it, as on a
    spinning wheel or ball), by the learned physics' own rigid motion at the handover: the twist
    ``(v at its centre [3], w [3], residual, acceleration [3], angular acceleration [3])`` that best
    fits f_trd's particle velocities over it. A turn about an axis near its centre (``AXLE``) is a
    hinge, a motion without a turn a rail, any other a free body; a group that f_trd moves as no one
    body is fixed."""
    v, w, residual, acceleration, angular = twist
    centre = points.mean(0)
    radius = _rms_radius(points, centre)
    common = {"name": name, "rows": rows, "points": points, "source": "learned physics"}
    held = "the learned physics (no model adopted) at the handover, its acceleration held"
    if residual > TWIST_RESIDUAL:
        why = f"not one rigid body (residual {rigid:.2f} of its radius): fixed where it is at the handover"
        return Body(joint="fixed", axis=np.zeros(3), pivot=centre, why=why, **common)
    turn, speed = float(np.linalg.norm(w)), float(np.linalg.norm(v))
    if turn * radius > SCREW * speed:
        axis = w / turn
        pivot = centre + np.cross(w, v) / turn**2  # where the twist's velocity is along its axis
        if abs(v @ axis) < SCREW * turn * radius and np.linalg.norm(pivot - centre) < AXLE * radius:
            rate = float(angular @ axis)
            model = IdentifiedModel(
                [("1", -1)], np.array([[rate]]), (True,), 0.0, np.zeros(1), np.array([turn])
            )
            return Body(
                joint="hinge", axis=axis, pivot=pivot, model=model, velocity=np.array([turn]),
                why=f"{held}: a turn about an axis through it", **common,
            )  # fmt: skip
    if turn * radius < SCREW * speed:
        axis = v / max(speed, 1e-300)
        model = IdentifiedModel([("1", -1)], np.array([[float(acceleration @ axis)]]), (False,), 0.0,
                                np.zeros(1), np.array([speed]))  # fmt: skip
        return Body(
            joint="slide", axis=axis, pivot=np.zeros(3), model=model, velocity=np.array([speed]),
            why=f"{held}: a motion without a turn", **common,
        )  # fmt: skip
    return Body(
        joint="free", axis=np.zeros(3), pivot=centre, velocity=np.concatenate([v, w]),
        acceleration=acceleration, why=f"{held}: a free body", **common,
    )  # fmt: skip


@torch.no_grad()
def _twist(model, x0: torch.Tensor, t0: float) -> tuple:
    """The twist of f_trd's particle velocities over the Gaussians at ``x0`` [M, 3] at ``t0``
    (``_twist_body``), refitted to the ``TWIST_INLIERS`` it fits best (a group's edge can hold
    Gaussians of the still part it touches), and the residual there relative to their RMS speed."""
    params = model.query_dynamics(x0, t0)
    u = particle_velocity(x0, params.velocity, params.angular_velocity).double()
    x, centre = x0.double(), x0.double().mean(0)
    keep = torch.ones(len(x), dtype=torch.bool, device=x.device)
    for _ in range(2):
        v, w = (c.to(x.device) for c in fit_rigid_velocity(x[keep], u[keep], centre))
        error = (u - v - torch.cross(w.expand_as(x), x - centre, dim=-1)).norm(dim=-1)
        keep = error <= error.quantile(TWIST_INLIERS)
    residual = float(
        error[keep].square().mean().sqrt() / u[keep].norm(dim=-1).square().mean().sqrt().clamp_min(1e-300)
    )
    return (
        _np(v), _np(w), residual, _np(params.acceleration.double().mean(0)),
        _np(params.angular_acceleration.double().mean(0)),
    )  # fmt: skip


def _distinct_joints(parts: list[Body]) -> bool:
    """Whether the rigid parts of a group turn or slide on joints of their own: each on a hinge or a
    rail, two of them of different kinds or axes more than ``DISTINCT_AXES`` apart."""
    if len(parts) < 2 or any(p.joint not in ("hinge", "slide") for p in parts):
        return False
    return any(
        a.joint != b.joint or abs(float(a.axis @ b.axis)) < math.cos(DISTINCT_AXES)
        for i, a in enumerate(parts)
        for b in parts[i + 1 :]
    )


def _carried(bodies: list[Body], start: torch.Tensor, path: list[torch.Tensor], times, settings) -> None:
    """Each free body (a free body of the run, or one on the learned physics) that turns or slides on a
    joint of its own in the frame of a larger body (a wing on a drifting satellite, a chain's second
    link) becomes that body's child on that joint: its path in the other's frame (f_defo's rigid
    transforms of that body) carried by a hinge or a rail (``_on_joint``), the body whose joint fits
    it best; in place. Its motion is then its joint's, moving on at its velocity there."""
    if not any(b.joint == "free" and b.source != "identified model" for b in bodies):
        return
    frames = {}
    for k, body in enumerate(bodies):
        if int(body.rows.sum()) >= MIN_GAUSSIANS:
            x = start[body.rows].double().cpu()
            frames[k] = part_transforms(x, [p[body.rows].double().cpu() for p in path])
    parents: set[int] = set()
    for k in sorted(range(len(bodies)), key=lambda i: int(bodies[i].rows.sum())):  # the smallest first
        body = bodies[k]
        if body.source == "identified model" or body.joint != "free" or body.parent is not None:
            continue
        track = torch.stack([p[body.rows].double().cpu() for p in path])
        best = None
        for j, (rotation, translation) in frames.items():  # a carrier is larger than what it carries
            if j == k or bodies[j].parent is not None or int(bodies[j].rows.sum()) <= int(body.rows.sum()):
                continue
            relative = (track - translation[:, None]) @ rotation  # R^T (x - T), row vectors
            child, _, score = _on_joint(body.name, body.rows, relative[-1], list(relative), times, settings)
            if child is not None and (best is None or score < best[0]):
                best = (score, j, child)
        if best is not None and k not in parents:
            _, j, child = best
            child.parent, child.why = (
                j,
                child.why.replace("on the joint", f"on a joint in {bodies[j].name}'s frame"),
            )
            bodies[k] = child
            parents.add(j)


@torch.no_grad()
def find_rig(predictor, extent: float, up: np.ndarray | None = None) -> Rig:
    """The rig of the trained run ``predictor`` (``extrapolate.Predictor``; ``extent``: the scene's
    size), its up ``up`` (default +z)."""
    model, state, settings = predictor.model, predictor.state, predictor.settings
    t0 = predictor.handover_time()
    start = model.deform(t0)["means"]
    taken = torch.zeros(start.shape[0], dtype=torch.bool, device=start.device)
    bodies: list[Body] = []
    joints, free = state.joint_laws, state.free_bodies
    if joints is not None and settings.joint_laws and abs(joints["t0"] - t0) < 1e-9:
        labels = joints["labels"].to(start.device)
        for k, part in enumerate(joints["parts"]):
            rows = labels == k + 1
            bodies.append(_from_part(k, part, rows, _np(start[rows])))
            taken |= rows
    if free is not None and settings.free_bodies and abs(free["t0"] - t0) < 1e-9:
        labels = free["labels"].to(start.device)
        for k, row in enumerate(free["bodies"]):
            rows = (labels == k + 1) & ~taken
            if bool(rows.any()):
                bodies.append(_from_free_body(k, row, rows, _np(start[rows])))
                taken |= rows
    times = np.array(frame_times(model, t0))
    path = [model.deform(float(t))["means"] for t in times]
    _, _, u, groups = moving_groups(predictor, t0, extent, settings.free_body_window)
    for label in range(1, int(groups.max()) + 1 if groups.numel() else 1):
        rows = (groups == label) & ~taken
        if int(rows.sum()) < MIN_GAUSSIANS:
            continue
        whole, _, _ = _on_joint(f"group{label}", rows, start[rows], [p[rows] for p in path], times, settings)
        # its rigid parts (as a joint part's group is cut): each on a joint, or by its twist; a group on
        # one joint stays one body unless its parts turn on joints of their own (a tray on a seat)
        split = split_parts(start, u, path, times, rows, 0.0025 * extent).to(rows.device)
        pieces = [rows.clone().index_put_((rows,), split == k) for k in range(1, int(split.max()) + 1)]
        pieces = [p for p in pieces if int(p.sum()) >= MIN_GAUSSIANS] or [rows]
        parts = []
        for i, piece in enumerate(pieces):
            name = f"group{label}" + (f"_{i + 1}" if len(pieces) > 1 else "")
            x0 = start[piece]
            body, rigid, _ = _on_joint(name, piece, x0, [p[piece] for p in path], times, settings)
            parts.append(body or _twist_body(name, piece, _np(x0), _twist(model, x0, t0), rigid))
        if whole is not None and not _distinct_joints(parts):
            parts = [whole]
        bodies += parts
        taken |= rows
    _carried(bodies, start, path, times, settings)
    return Rig(t0, bodies, np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float))
