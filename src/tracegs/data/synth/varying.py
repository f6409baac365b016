"""Part motions under forces that are not constant, in closed form: a damped pendulum or spring, a
friction stop, a bouncing ball, and a part carried by another part.

Each is exact at any t (t > 1 included) and is the identity at t = 0 (the meshes are built in the
pose of t = 0). Angles and displacements are about a ``pivot`` (a point of the part at t = 0) and
along a unit ``axis`` or ``direction`` in world coordinates; units are scene units and radians per
unit of t, as for :class:`~tracegs.data.synth.motion.RigidMotion`.

# T: times (any leading shape ...)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from .kinematics import Motion, axis_angle_to_matrix, damped_oscillation, plain, rigid_transform, unit

_DAMPED = "s(t) = A exp(-zeta*w0*t) cos(w0*sqrt(1-zeta^2)*t + phi); "
FORMULAS = {
    "damped_rotation": _DAMPED + "x(t) = R(axis, s(t) - s(0)) (x0 - pivot) + pivot",
    "damped_translation": _DAMPED + "x(t) = x0 + (s(t) - s(0)) direction",
    "friction_stop": (
        "tau = min(t, stop_time), stop_time = -w/alpha; theta(t) = w*tau + alpha*tau^2/2; "
        "x(t) = R(axis, theta(t)) (x0 - pivot) + pivot"
    ),
    "bouncing": (
        "pivot height: parabolas under gravity g between floor contacts, vertical speed times -e at each "
        "contact, at rest after the last; horizontal: v*t; spin: R(axis, w*t) about the pivot"
    ),
    "carried": "T(t) = T_parent(t) T_child(t): the child's motion is in the parent's rest frame",
}
"""Motion type -> its closed form, as ``gt/motion.json`` states it."""


@dataclass(frozen=True)
class _Oscillator:
    """The parameters of s(t) = A e^{-zeta w0 t} cos(w_d t + phi), shared by the damped motions."""

    amplitude: float = 0.0
    """A: the envelope of s at t = 0 (radians or scene units)."""
    phase: float = 0.0
    """phi: phase at t = 0 (radians)."""
    natural_frequency: float = 1.0
    """w0: undamped angular frequency (radians per unit of t); the stiffness per inertia is w0^2."""
    damping_ratio: float = 0.0
    """zeta in [0, 1): damping per inertia is 2 zeta w0; the amplitude decays as exp(-zeta w0 t)."""

    def __post_init__(self):
        if not self.natural_frequency > 0:
            raise ValueError(f"natural_frequency must be > 0, got {self.natural_frequency}")
        if not 0 <= self.damping_ratio < 1:
            raise ValueError(f"damping_ratio must be in [0, 1) (under-damped), got {self.damping_ratio}")

    def value(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(s(t), s'(t)): s measured from the equilibrium, the rest pose is s(0)."""
        return damped_oscillation(t, self.amplitude, self.phase, self.natural_frequency, self.damping_ratio)

    def offset(self, t) -> np.ndarray:
        """s(t) - s(0): how far the part has moved from its rest pose."""
        return self.value(t)[0] - self.value(0.0)[0]

    def record(self) -> dict:
        """The parameters, and values a reader would otherwise recompute: w_d, the decay rate, s(0)."""
        return {
            "type": self.kind,
            **plain(asdict(self)),
            "damped_frequency": self.natural_frequency * float(np.sqrt(1 - self.damping_ratio**2)),
            "decay_rate": self.damping_ratio * self.natural_frequency,
            "rest_offset": float(self.value(0.0)[0]),
        }


@dataclass(frozen=True)
class DampedRotation(_Oscillator):
    """A damped pendulum (small-angle, or a torsion spring): the angle about ``axis`` through ``pivot``,
    measured from the equilibrium, is s(t)."""

    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    kind = "damped_rotation"

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "axis", unit(self.axis, "axis"))

    def transform(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        R = axis_angle_to_matrix(self.axis, self.offset(t))
        return rigid_transform(R, self.pivot, np.zeros((*t.shape, 3)))

    def angular_velocity_at(self, t) -> np.ndarray:
        return self.value(t)[1][..., None] * np.asarray(self.axis)


@dataclass(frozen=True)
class DampedTranslation(_Oscillator):
    """A mass on a spring: its displacement along ``direction``, from the equilibrium, is s(t)."""

    direction: tuple[float, float, float] = (1.0, 0.0, 0.0)
    kind = "damped_translation"

    def __post_init__(self):
        super().__post_init__()
        object.__setattr__(self, "direction", unit(self.direction, "direction"))

    def transform(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        shift = self.offset(t)[..., None] * np.asarray(self.direction)
        return rigid_transform(np.broadcast_to(np.eye(3), (*t.shape, 3, 3)), np.zeros(3), shift)

    def angular_velocity_at(self, t) -> np.ndarray:
        return np.zeros((*np.shape(t), 3))


@dataclass(frozen=True)
class FrictionStop:
    """A wheel braking to rest: constant angular acceleration ``angular_acceleration`` (opposite to
    ``angular_velocity``) until the spin is 0 at ``stop_time``, then still (static friction holds)."""

    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular_velocity: float = 1.0
    """w: angular velocity about ``axis`` at t = 0."""
    angular_acceleration: float = -1.0
    """alpha: the braking angular acceleration, of the opposite sign to w."""
    kind = "friction_stop"

    def __post_init__(self):
        object.__setattr__(self, "axis", unit(self.axis, "axis"))
        if not self.angular_velocity * self.angular_acceleration < 0:
            raise ValueError(
                "a friction stop needs angular_velocity and angular_acceleration of opposite signs, got "
                f"{self.angular_velocity} and {self.angular_acceleration}"
            )

    @property
    def stop_time(self) -> float:
        return -self.angular_velocity / self.angular_acceleration

    def _tau(self, t) -> np.ndarray:
        return np.minimum(np.asarray(t, dtype=np.float64), self.stop_time)

    def angle(self, t) -> np.ndarray:
        """theta(t) [...]: w tau + alpha tau^2 / 2 with tau = min(t, stop_time)."""
        tau = self._tau(t)
        return self.angular_velocity * tau + 0.5 * self.angular_acceleration * tau**2

    def transform(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        R = axis_angle_to_matrix(self.axis, self.angle(t))
        return rigid_transform(R, self.pivot, np.zeros((*t.shape, 3)))

    def angular_velocity_at(self, t) -> np.ndarray:
        rate = self.angular_velocity + self.angular_acceleration * self._tau(t)
        return rate[..., None] * np.asarray(self.axis)

    def record(self) -> dict:
        return {"type": self.kind, **plain(asdict(self)), "stop_time": self.stop_time}


MAX_BOUNCES = 200
"""Contacts computed before the ball is put at rest (the Zeno limit of the contact times)."""


@dataclass(frozen=True)
class Bouncing:
    """A ball bouncing on a horizontal floor with restitution ``restitution``: its centre (``pivot`` at
    t = 0) flies on parabolas under gravity ``gravity`` (along -z), its vertical speed is reversed and
    scaled by ``restitution`` at each contact (height ``floor_height``), and it rests on the floor once
    the contact times converge. The horizontal velocity stays (frictionless floor); the ball spins at
    the constant ``angular_velocity`` about ``axis`` through its centre."""

    pivot: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """The ball's centre at t = 0."""
    linear_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """v: the centre's velocity at t = 0 (its horizontal part is kept for all t)."""
    gravity: float = 9.81
    """g > 0: downward acceleration (scene units per unit of t^2)."""
    floor_height: float = 0.0
    """z of the centre at contact: the floor's height plus the ball's radius."""
    restitution: float = 0.5
    """e in [0, 1): rebound vertical speed over impact speed."""
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    angular_velocity: float = 0.0
    """w: the constant spin about ``axis``."""
    kind = "bouncing"

    def __post_init__(self):
        object.__setattr__(self, "axis", unit(self.axis, "axis"))
        if not self.gravity > 0:
            raise ValueError(f"gravity must be > 0, got {self.gravity}")
        if not 0 <= self.restitution < 1:
            raise ValueError(f"restitution must be in [0, 1), got {self.restitution}")
        if self.pivot[2] < self.floor_height:
            raise ValueError(f"the ball starts below the floor: z {self.pivot[2]} < {self.floor_height}")

    def arcs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Start time, height, upward speed and gravity [K] of each flight: the throw, one arc per
        contact, and the rest on the floor (gravity 0) from the limit of the contact times."""
        z0, vz, g = self.pivot[2] - self.floor_height, self.linear_velocity[2], self.gravity
        t1 = (vz + np.sqrt(vz**2 + 2 * g * z0)) / g  # first contact: z0 + vz t - g t^2 / 2 = 0
        speeds = np.sqrt(vz**2 + 2 * g * z0) * self.restitution ** np.arange(1, MAX_BOUNCES + 1)
        speeds = speeds[speeds > 1e-12]
        contacts = t1 + np.concatenate([[0.0], np.cumsum(2 * speeds / g)])  # contacts[-1]: at rest
        starts = np.concatenate([[0.0], contacts])
        heights = np.concatenate([[z0], np.zeros(len(contacts))])
        upward = np.concatenate([[vz], speeds, [0.0]])
        gravity = np.concatenate([np.full(len(contacts), g), [0.0]])
        return starts, heights + self.floor_height, upward, gravity

    def contact_times(self) -> np.ndarray:
        """[K] times at which the ball touches the floor (after the last one it rests)."""
        return self.arcs()[0][1:-1]

    def centre(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(position [..., 3], velocity [..., 3]) of the centre at times ``t`` [...]; at a contact time the
        velocity is the one after the bounce."""
        t = np.asarray(t, dtype=np.float64)
        starts, heights, upward, gravity = self.arcs()
        k = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
        tau = t - starts[k]
        v = np.asarray(self.linear_velocity, dtype=np.float64)
        position = np.asarray(self.pivot, dtype=np.float64) + v * t[..., None]
        position[..., 2] = heights[k] + upward[k] * tau - 0.5 * gravity[k] * tau**2
        velocity = np.broadcast_to(v, (*t.shape, 3)).copy()
        velocity[..., 2] = upward[k] - gravity[k] * tau
        return position, velocity

    def transform(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        R = axis_angle_to_matrix(self.axis, self.angular_velocity * t)
        return rigid_transform(R, self.pivot, self.centre(t)[0] - np.asarray(self.pivot))

    def angular_velocity_at(self, t) -> np.ndarray:
        return np.broadcast_to(self.angular_velocity * np.asarray(self.axis), (*np.shape(t), 3)).copy()

    def record(self) -> dict:
        first = self.contact_times()[:8].tolist()
        return {"type": self.kind, **plain(asdict(self)), "first_contact_times": first}


@dataclass(frozen=True)
class Carried:
    """A part moved by ``child`` in the rest frame of another part that moves by ``parent`` (a box
    spinning on a turntable): T(t) = T_parent(t) T_child(t)."""

    parent: Motion
    child: Motion
    parent_part: int | None = None
    """Mask id of the part whose motion ``parent`` is, when it is one of the scene's parts."""
    kind = "carried"

    def transform(self, t) -> np.ndarray:
        return self.parent.transform(t) @ self.child.transform(t)

    def angular_velocity_at(self, t) -> np.ndarray:
        R = self.parent.transform(t)[..., :3, :3]
        return self.parent.angular_velocity_at(t) + (R @ self.child.angular_velocity_at(t)[..., None])[..., 0]

    def record(self) -> dict:
        d = {"type": self.kind, "parent": self.parent.record(), "child": self.child.record()}
        return d if self.parent_part is None else {**d, "parent_part": self.parent_part}


CLOSED_FORMS = {cls.kind: cls for cls in (DampedRotation, DampedTranslation, FrictionStop, Bouncing)}
"""Record ``type`` -> the dataclass whose fields the record holds (``carried`` nests two records)."""
