"""What every part motion of the synthetic scenes provides, and the closed forms they share.

A motion maps times to rest-pose -> world rigid transforms (identity at t = 0: the meshes are built in
the pose of t = 0), gives its world angular velocity, and writes itself as a json record that
:func:`~tracegs.data.synth.motion.motion_from_record` reads back.

# T: times (any leading shape ...)
"""

from __future__ import annotations

from dataclasses import fields
from typing import Protocol

import numpy as np


class Motion(Protocol):
    """One rigid part's motion, exact at any time t (t > 1 included)."""

    kind: str
    """The ``type`` of its record in ``gt/motion.json``."""

    def transform(self, t) -> np.ndarray:
        """[..., 4, 4] rest-pose -> world rigid transform at times ``t`` [...]."""
        ...

    def angular_velocity_at(self, t) -> np.ndarray:
        """[..., 3] world angular velocity at times ``t`` [...] (radians per unit of t)."""
        ...

    def record(self) -> dict:
        """``type`` and the parameters (plain json values) that recompute the motion."""
        ...


def unit(v, what: str) -> tuple[float, float, float]:
    """``v`` normalised; a zero or non-finite vector raises ``ValueError`` naming ``what``."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v)
    if v.shape != (3,) or not np.isfinite(n) or n < 1e-9:
        raise ValueError(f"{what} must be a non-zero 3-vector, got {v.tolist()}")
    return tuple(float(x) / n for x in v)


def axis_angle_to_matrix(axis, angle: np.ndarray) -> np.ndarray:
    """[..., 3, 3] Rodrigues rotation about the unit ``axis`` by ``angle`` [...]."""
    a = np.asarray(axis, dtype=np.float64)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    angle = np.asarray(angle, dtype=np.float64)[..., None, None]
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def rigid_transform(rotation: np.ndarray, pivot, displacement: np.ndarray) -> np.ndarray:
    """[..., 4, 4] x -> rotation (x - pivot) + pivot + displacement, for rotation [..., 3, 3] and
    displacement [..., 3]."""
    pivot = np.asarray(pivot, dtype=np.float64)
    out = np.zeros((*rotation.shape[:-2], 4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = pivot - rotation @ pivot + displacement
    out[..., 3, 3] = 1.0
    return out


def damped_oscillation(t, amplitude: float, phase: float, natural_frequency: float, damping_ratio: float):
    """(s, ds/dt), each shaped like ``t``: s(t) = A e^{-zeta w0 t} cos(w_d t + phi), w_d = w0 sqrt(1 -
    zeta^2), the solution of s'' + 2 zeta w0 s' + w0^2 s = 0 (a linear spring-damper, under-damped)."""
    t = np.asarray(t, dtype=np.float64)
    decay = damping_ratio * natural_frequency
    w_d = natural_frequency * np.sqrt(1.0 - damping_ratio**2)
    envelope = amplitude * np.exp(-decay * t)
    psi = w_d * t + phase
    return envelope * np.cos(psi), -envelope * (decay * np.cos(psi) + w_d * np.sin(psi))


def plain(value):
    """Tuples -> lists, numpy scalars -> floats, recursively: a json-ready copy."""
    if isinstance(value, dict):
        return {k: plain(v) for k, v in value.items()}
    if isinstance(value, tuple | list):
        return [plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def from_fields(cls, record: dict, **extra):
    """``cls(**...)`` from the keys of ``record`` that are fields of the dataclass ``cls`` (lists
    become tuples); other keys, such as derived values and notes, are ignored."""
    names = {f.name for f in fields(cls)}
    kwargs = {k: (tuple(v) if isinstance(v, list) else v) for k, v in record.items() if k in names}
    return cls(**kwargs, **extra)
