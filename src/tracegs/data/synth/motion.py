"""Closed-form rigid motion of the synthetic parts, and its ground-truth file ``gt/motion.json``.

Each part moves by one formula with constant angular and linear acceleration (the translation-rotation
dynamics TRACE learns), evaluated exactly at any time, including t > 1 for extrapolation:

    theta(t) = w t + 1/2 alpha t^2                       (angle about the fixed unit ``axis``)
    x(t)     = R(axis, theta(t)) (x0 - pivot) + pivot + v t + 1/2 a t^2

x0 is a point of the part in the rest pose (t = 0), so every transform is the identity at t = 0.
The rotation is about a line through ``pivot`` fixed in the part, which the translation carries
along (a door on a drifting satellite, a ball spinning about its own moving centre).

Parts under forces that are not constant (a pendulum, a spring, a friction stop, a bounce, a part
carried by another) move by the closed forms of :mod:`.varying`, parts with several coupled degrees
of freedom by the integrated motions of :mod:`.mechanisms` and the impact of :mod:`.impacts`; every motion follows the
:class:`~.kinematics.Motion` protocol (``transform``, ``angular_velocity_at``, ``record``) and
:func:`motion_from_record` reads any of them back from ``gt/motion.json``.

# T: times, P: parts
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from . import impacts, mechanisms
from .kinematics import Motion, axis_angle_to_matrix, from_fields, plain, rigid_transform, unit
from .varying import CLOSED_FORMS, FORMULAS, Carried

FORMULA = "theta(t) = w*t + alpha*t^2/2; x(t) = R(axis, theta(t)) (x0 - pivot) + pivot + v*t + a*t^2/2"
MOTION_TYPES = {
    **CLOSED_FORMS,
    **mechanisms.INTEGRATED,
    impacts.SlidingCollision.kind: impacts.SlidingCollision,
}
"""Record ``type`` -> the dataclass whose fields the record holds (``carried`` nests two records)."""
EQUATIONS = {**FORMULAS, **mechanisms.FORMULAS, **impacts.FORMULAS}
"""Motion type -> its closed form or equations of motion, as ``gt/motion.json`` states them."""


@dataclass(frozen=True)
class RigidMotion:
    """Parameters of one part's closed-form motion; units are scene units and radians per unit t."""

    kind: str = "static"
    """Label only: static, rotation, translation, rotation+translation, projectile."""
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """Unit rotation axis (right-handed), in world coordinates of the rest pose."""
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """A point on the rotation axis at t = 0; it moves with the part's translation."""
    angular_velocity: float = 0.0
    """w: angular velocity about ``axis`` at t = 0."""
    angular_acceleration: float = 0.0
    """alpha: constant angular acceleration about ``axis``."""
    linear_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """v: velocity of the pivot at t = 0."""
    linear_acceleration: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """a: constant acceleration of the pivot (gravity for a projectile)."""

    def __post_init__(self):
        object.__setattr__(self, "axis", unit(self.axis, "rotation axis"))

    def transform(self, t) -> np.ndarray:
        """[..., 4, 4] rest-pose -> world at times ``t`` [...] (:func:`motion_transform`)."""
        return motion_transform(self, t)

    def angular_velocity_at(self, t) -> np.ndarray:
        """[..., 3] (w + alpha t) axis."""
        rate = self.angular_velocity + self.angular_acceleration * np.asarray(t, dtype=np.float64)
        return rate[..., None] * np.asarray(self.axis)

    def record(self) -> dict:
        """``type`` (the label ``kind``) and the fields."""
        fields = plain(asdict(self))
        fields.pop("kind")
        return {"type": self.kind, **fields}


def rotation_angle(motion: RigidMotion, t: np.ndarray) -> np.ndarray:
    """theta(t) = w t + alpha t^2 / 2, same shape as ``t``."""
    t = np.asarray(t, dtype=np.float64)
    return motion.angular_velocity * t + 0.5 * motion.angular_acceleration * t**2


def pivot_displacement(motion: RigidMotion, t: np.ndarray) -> np.ndarray:
    """[..., 3] v t + a t^2 / 2."""
    t = np.asarray(t, dtype=np.float64)[..., None]
    return np.asarray(motion.linear_velocity) * t + 0.5 * np.asarray(motion.linear_acceleration) * t**2


def motion_transform(motion: RigidMotion, t) -> np.ndarray:
    """[..., 4, 4] rest-pose -> world rigid transform of the part at times ``t`` [...]."""
    t = np.asarray(t, dtype=np.float64)
    R = axis_angle_to_matrix(motion.axis, rotation_angle(motion, t))
    return rigid_transform(R, motion.pivot, pivot_displacement(motion, t))


def transforms_at(motions: list[Motion], t) -> np.ndarray:
    """[P, 4, 4] for a scalar ``t``, [T, P, 4, 4] for times [T]."""
    return np.stack([m.transform(t) for m in motions], axis=-3)


def angular_velocities_at(motions: list[Motion], t) -> np.ndarray:
    """[P, 3] world angular velocities for a scalar ``t``, [T, P, 3] for times [T]."""
    return np.stack([m.angular_velocity_at(t) for m in motions], axis=-2)


def motion_record(name: str, part_id: int, motion: Motion) -> dict:
    """One part's entry in ``gt/motion.json``."""
    return {"name": name, "id": part_id, **motion.record()}


def motion_from_record(record: dict) -> Motion:
    """Inverse of :func:`motion_record` and of every motion's ``record`` (unknown keys, such as notes
    and derived values, are ignored); a ``type`` of no other motion is a :class:`RigidMotion` label."""
    kind = record.get("type", "static")
    if kind == Carried.kind:
        parent, child = motion_from_record(record["parent"]), motion_from_record(record["child"])
        return Carried(parent, child, record.get("parent_part"))
    if kind in MOTION_TYPES:
        return from_fields(MOTION_TYPES[kind], record)
    return from_fields(RigidMotion, record, kind=kind)


def load_motions(source) -> list[Motion]:
    """Motions ordered by part id from an output folder, its ``gt`` folder, a ``motion.json`` path or
    the parsed json dict."""
    if isinstance(source, dict):
        data = source
    else:
        path = Path(source)
        for candidate in (path, path / "gt" / "motion.json", path / "motion.json"):
            if candidate.is_file():
                path = candidate
                break
        else:
            raise FileNotFoundError(f"no motion.json at {path} (nor {path / 'gt' / 'motion.json'})")
        data = json.loads(path.read_text())
    parts = sorted(data["parts"], key=lambda p: p["id"])
    if [p["id"] for p in parts] != list(range(1, len(parts) + 1)):
        raise ValueError("motion.json part ids must be 1..P")
    return [motion_from_record(p) for p in parts]


def part_transforms(out_or_motion_json, t) -> np.ndarray:
    """Rest-pose -> world rigid transform of every part at time(s) ``t`` from the closed form.

    ``out_or_motion_json``: a ``tracegs synth`` output folder, its ``gt/motion.json`` (path or parsed
    dict). ``t``: a float -> [P, 4, 4], or an array [T] -> [T, P, 4, 4]; any t, also beyond 1.
    Index p holds the part whose mask id is p + 1 (0 is the background).
    """
    return transforms_at(load_motions(out_or_motion_json), t)


def part_angular_velocities(out_or_motion_json, t) -> np.ndarray:
    """World angular velocity of every part at time(s) ``t`` from the closed form: [P, 3] for a float,
    [T, P, 3] for times [T]; the same sources and part order as :func:`part_transforms`."""
    return angular_velocities_at(load_motions(out_or_motion_json), t)
