"""Part motions with several coupled degrees of freedom, integrated exactly (:mod:`.integrate`): a ball
rolling without slipping in a spherical bowl, a gyroscope precessing on a pivot, a chain of hinged
links swinging under gravity, and a disc held by springs in a plane.

Each is a frozen dataclass holding the constants and the state at t = 0 (its ``gt/motion.json``
record); a mechanism of several parts (the chain) is one record per part, equal but for the index of
the part (``link``). Every transform is the identity at t = 0 (the meshes are built in the pose of
t = 0); units are scene units, radians and units of t; masses and inertias are per the part's mass
where only ratios matter.

# T: times (any leading shape ...), N: links
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from .integrate import quaternion_rate, quaternion_to_matrix, trajectory_of
from .kinematics import axis_angle_to_matrix, plain, rigid_transform, unit

FORMULAS = {
    "rolling_ball": (
        "a solid ball (I = 2/5 m r^2) rolling without slipping inside a sphere (centre bowl_center, "
        "radius bowl_radius) under gravity g along -z: centre c on the sphere of radius rho = R - r about "
        "the bowl's centre, n = (c - O) / rho; c'' = 5/7 g_t + 2/7 (r / rho) normal_spin (c' x n) - "
        "|c'|^2 / rho n (g_t: gravity's part tangent to the sphere); spin w = (c' x n) / r + "
        "normal_spin n (no slip at the contact c + r n); x(t) = R(t) (x0 - c(0)) + c(t), R' = [w]x R"
    ),
    "gyroscope": (
        "a symmetric body on a fixed pivot under gravity g along -z (per unit mass: centre of mass at "
        "com_distance along its symmetry axis a, inertias transverse_inertia I1 and axial_inertia I3 "
        "about the pivot): L' = com_distance a x (0, 0, -g), w = (L - (L.a) a) / I1 + (L.a) a / I3, "
        "R' = [w]x R, a(t) = R(t) a(0); x(t) = R(t) (x0 - pivot) + pivot"
    ),
    "hinged_chain": (
        "uniform bars on parallel hinges (axis) hanging from pivot, link k of length L_k and mass m_k "
        "at absolute angle theta_k from hanging straight down: sum_j M_kj theta_j'' + sum_j C_kj "
        "sin(theta_k - theta_j) theta_j'^2 + g sin(theta_k) sum_i m_i a_ik = 0, a_ik = L_k (k < i), "
        "L_k / 2 (k = i), 0 (k > i), C = a^T diag(m) a, M = C cos(theta_k - theta_j) + diag(m L^2 / 12); "
        "link k: x(t) = R(axis, theta_k(t) - theta_k(0)) (x0 - J_k(0)) + J_k(t), J_k its upper joint"
    ),
    "planar_springs": (
        "a rigid disc sliding in the plane z = const (mass, inertia about its centre) pulled by linear "
        "springs from fixed anchors to points of the disc (attachments, at t = 0): force k_i (|d_i| - "
        "l_i) d_i / |d_i|, d_i = anchor_i - attachment_i(t), torque of each about the centre, viscous "
        "damping on the centre's velocity and the spin; x(t) = R(z, phi(t)) (x0 - c(0)) + c(t)"
    ),
}
"""Motion type -> its equations, as ``gt/motion.json`` states them."""

DOWN = np.array([0.0, 0.0, -1.0])


def _vec(v) -> np.ndarray:
    return np.asarray(v, dtype=np.float64)


@dataclass(frozen=True)
class RollingBall:
    """A solid ball of radius ``ball_radius`` rolling without slipping inside a spherical bowl."""

    bowl_center: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """O: the centre of the bowl's sphere."""
    bowl_radius: float = 1.0
    """R: the radius of the bowl's inner surface."""
    ball_radius: float = 0.1
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.1)
    """c(0): the ball's centre at t = 0, at R - r from O."""
    linear_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """c'(0): tangent to the sphere of the centre."""
    normal_spin: float = 0.0
    """w . n: the spin about the normal at the contact (conserved)."""
    gravity: float = 9.81
    kind = "rolling_ball"

    def __post_init__(self):
        rho = self.bowl_radius - self.ball_radius
        if not (self.ball_radius > 0 and rho > 0 and self.gravity > 0):
            raise ValueError(f"need 0 < ball_radius < bowl_radius and gravity > 0, got {self}")
        offset = _vec(self.pivot) - _vec(self.bowl_center)
        if abs(np.linalg.norm(offset) - rho) > 1e-9 or abs(offset @ _vec(self.linear_velocity)) > 1e-9 * rho:
            raise ValueError("the ball's centre must start on the sphere of radius R - r, moving along it")

    def initial_state(self) -> np.ndarray:
        return np.concatenate([self.pivot, self.linear_velocity, [1.0, 0.0, 0.0, 0.0]])

    def _normal(self, c: np.ndarray) -> np.ndarray:
        n = c - _vec(self.bowl_center)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def spin(self, velocity: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """[..., 3] the world angular velocity that rolls without slipping: (c' x n) / r + spin n."""
        return np.cross(velocity, normal) / self.ball_radius + self.normal_spin * normal

    def derivative(self, t: float, y: np.ndarray) -> np.ndarray:
        c, v, q = y[:3], y[3:6], y[6:]
        n, rho = self._normal(c), self.bowl_radius - self.ball_radius
        g = self.gravity * DOWN
        g_t = g - (g @ n) * n
        a = (
            5 / 7 * g_t
            + 2 / 7 * (self.ball_radius / rho) * self.normal_spin * np.cross(v, n)
            - (v @ v) / rho * n
        )
        return np.concatenate([v, a, quaternion_rate(q, self.spin(v, n))])

    def state(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(centre [..., 3] on the sphere, velocity [..., 3], rotation since t = 0 [..., 3, 3])."""
        y = trajectory_of(self)(t)
        rho = self.bowl_radius - self.ball_radius
        return (
            _vec(self.bowl_center) + rho * self._normal(y[..., :3]),
            y[..., 3:6],
            quaternion_to_matrix(y[..., 6:]),
        )

    def transform(self, t) -> np.ndarray:
        c, _, R = self.state(t)
        return rigid_transform(R, self.pivot, c - _vec(self.pivot))

    def angular_velocity_at(self, t) -> np.ndarray:
        c, v, _ = self.state(t)
        return self.spin(v, self._normal(c))

    def record(self) -> dict:
        rho = self.bowl_radius - self.ball_radius
        return {
            "type": self.kind,
            **plain(asdict(self)),
            "small_oscillation_frequency": float(np.sqrt(5 / 7 * self.gravity / rho)),
        }


@dataclass(frozen=True)
class Gyroscope:
    """A spinning symmetric body whose axis turns about a fixed ``pivot`` under gravity (a heavy top)."""

    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    """a(0): the symmetry axis at t = 0, pointing from the pivot towards the centre of mass."""
    com_distance: float = 0.3
    transverse_inertia: float = 0.1
    """I1: about an axis through the pivot perpendicular to the symmetry axis, per unit mass."""
    axial_inertia: float = 0.03
    """I3: about the symmetry axis, per unit mass."""
    spin: float = 10.0
    """w . a: the spin about the symmetry axis (conserved)."""
    precession_rate: float = 0.0
    """The rate at which the axis turns about +z at t = 0 (the angular velocity's part across the
    axis is this rate times the part of +z across the axis)."""
    gravity: float = 9.81
    kind = "gyroscope"

    def __post_init__(self):
        object.__setattr__(self, "axis", unit(self.axis, "axis"))
        if not (self.transverse_inertia > 0 and self.axial_inertia > 0 and self.gravity > 0):
            raise ValueError(f"inertias and gravity must be > 0, got {self}")

    def initial_state(self) -> np.ndarray:
        a = _vec(self.axis)
        up = np.array([0.0, 0.0, 1.0])
        omega = self.spin * a + self.precession_rate * (
            up - (up @ a) * a
        )  # the axis turns about z at this rate
        return np.concatenate([self._momentum(omega, a), [1.0, 0.0, 0.0, 0.0]])

    def _momentum(self, omega: np.ndarray, a: np.ndarray) -> np.ndarray:
        along = (omega * a).sum(-1, keepdims=True)
        return self.transverse_inertia * (omega - along * a) + self.axial_inertia * along * a

    def _omega(self, momentum: np.ndarray, a: np.ndarray) -> np.ndarray:
        along = (momentum * a).sum(-1, keepdims=True)
        return (momentum - along * a) / self.transverse_inertia + along * a / self.axial_inertia

    def derivative(self, t: float, y: np.ndarray) -> np.ndarray:
        L, q = y[:3], y[3:]
        a = quaternion_to_matrix(q) @ _vec(self.axis)
        torque = self.com_distance * np.cross(a, self.gravity * DOWN)
        return np.concatenate([torque, quaternion_rate(q, self._omega(L, a))])

    def state(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(rotation since t = 0 [..., 3, 3], world angular momentum per unit mass [..., 3])."""
        y = trajectory_of(self)(t)
        return quaternion_to_matrix(y[..., 3:]), y[..., :3]

    def transform(self, t) -> np.ndarray:
        R, _ = self.state(t)
        return rigid_transform(R, self.pivot, np.zeros((*R.shape[:-2], 3)))

    def angular_velocity_at(self, t) -> np.ndarray:
        R, L = self.state(t)
        return self._omega(L, R @ _vec(self.axis))

    def record(self) -> dict:
        return {"type": self.kind, **plain(asdict(self))}


@dataclass(frozen=True)
class HingedChain:
    """Uniform bars hanging from ``pivot`` on hinges parallel to ``axis``, each from the end of the
    one above (a double pendulum for two links); this record is the motion of the bar ``link``."""

    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 1.0, 0.0)
    lengths: tuple[float, ...] = (0.5, 0.4)
    masses: tuple[float, ...] = (1.0, 1.0)
    angles: tuple[float, ...] = (0.0, 0.0)
    """theta_k(0): each bar's angle about ``axis`` from hanging straight down."""
    rates: tuple[float, ...] = (0.0, 0.0)
    """theta_k'(0)."""
    gravity: float = 9.81
    link: int = 0
    """Which bar this part is (0: the one on the pivot)."""
    kind = "hinged_chain"

    def __post_init__(self):
        object.__setattr__(self, "axis", unit(self.axis, "axis"))
        n = len(self.lengths)
        if not (
            n >= 1 and len(self.masses) == len(self.angles) == len(self.rates) == n and 0 <= self.link < n
        ):
            raise ValueError(
                f"lengths, masses, angles and rates must all have one value per link, got {self}"
            )
        if abs(self.axis[2]) > 1e-9:
            raise ValueError(f"the hinge axis must be horizontal, got {self.axis}")

    def initial_state(self) -> np.ndarray:
        return np.concatenate([self.angles, self.rates])

    def coefficients(self) -> tuple[np.ndarray, np.ndarray]:
        """(C [N, N] = a^T diag(m) a, the gravity weights sum_i m_i a_ik [N]) of the equations."""
        L, m = _vec(self.lengths), _vec(self.masses)
        n = len(L)
        k = np.arange(n)
        a = np.where(k[None, :] < k[:, None], L[None, :], 0.0) + np.diag(L / 2)  # [i body, k angle]
        return a.T @ (m[:, None] * a), m @ a

    def derivative(self, t: float, y: np.ndarray) -> np.ndarray:
        n = len(self.lengths)
        theta, rate = y[:n], y[n:]
        C, weights = self.coefficients()
        diff = theta[:, None] - theta[None, :]
        M = C * np.cos(diff) + np.diag(_vec(self.masses) * _vec(self.lengths) ** 2 / 12)
        rhs = -(C * np.sin(diff)) @ rate**2 - self.gravity * weights * np.sin(theta)
        return np.concatenate([rate, np.linalg.solve(M, rhs)])

    def _system(self) -> HingedChain:
        return replace(self, link=0)

    def angles_at(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(theta [..., N], theta' [..., N])."""
        y = trajectory_of(self._system())(t)
        n = len(self.lengths)
        return y[..., :n], y[..., n:]

    def joint(self, theta: np.ndarray) -> np.ndarray:
        """[..., 3] the upper joint of bar ``link`` for the angles ``theta`` [..., N]."""
        ends = [
            self.lengths[j] * axis_angle_to_matrix(self.axis, theta[..., j]) @ DOWN for j in range(self.link)
        ]
        return _vec(self.pivot) + sum(ends, np.zeros((*theta.shape[:-1], 3)))

    def transform(self, t) -> np.ndarray:
        theta, _ = self.angles_at(t)
        theta0 = _vec(self.angles)
        R = axis_angle_to_matrix(self.axis, theta[..., self.link] - theta0[self.link])
        start = self.joint(theta0)
        return rigid_transform(R, start, self.joint(theta) - start)

    def angular_velocity_at(self, t) -> np.ndarray:
        return self.angles_at(t)[1][..., self.link, None] * _vec(self.axis)

    def record(self) -> dict:
        return {"type": self.kind, **plain(asdict(self))}


@dataclass(frozen=True)
class PlanarSprings:
    """A rigid disc sliding on a horizontal plane, pulled by springs from fixed anchors."""

    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """c(0): the disc's centre at t = 0 (its height stays)."""
    linear_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    angular_velocity: float = 0.0
    """phi'(0), about +z."""
    anchors: tuple[tuple[float, float, float], ...] = ()
    attachments: tuple[tuple[float, float, float], ...] = ()
    """Where each spring holds the disc, at t = 0."""
    stiffnesses: tuple[float, ...] = ()
    rest_lengths: tuple[float, ...] = ()
    mass: float = 1.0
    inertia: float = 0.01
    """About the disc's vertical axis through its centre."""
    damping: float = 0.0
    """Viscous: force -damping c', torque -damping phi' inertia / mass."""
    kind = "planar_springs"

    def __post_init__(self):
        for name in ("anchors", "attachments"):  # json lists of lists: hashable again
            object.__setattr__(self, name, tuple(tuple(float(x) for x in p) for p in getattr(self, name)))
        n = len(self.anchors)
        if not (n >= 2 and len(self.attachments) == len(self.stiffnesses) == len(self.rest_lengths) == n):
            raise ValueError(
                "anchors, attachments, stiffnesses and rest_lengths need one value per spring (2+)"
            )
        if not (self.mass > 0 and self.inertia > 0 and self.damping >= 0):
            raise ValueError(f"mass and inertia must be > 0 and damping >= 0, got {self}")

    def initial_state(self) -> np.ndarray:
        return np.array([*self.pivot[:2], 0.0, *self.linear_velocity[:2], self.angular_velocity])

    def spring_vectors(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lever arms [..., K, 2] from the centre, anchor - attachment [..., K, 2]) for states [..., 6]."""
        arms0 = _vec(self.attachments)[:, :2] - _vec(self.pivot)[:2]
        c, s = np.cos(y[..., 2, None, None]), np.sin(y[..., 2, None, None])
        arms = np.stack(
            [
                c[..., 0] * arms0[:, 0] - s[..., 0] * arms0[:, 1],
                s[..., 0] * arms0[:, 0] + c[..., 0] * arms0[:, 1],
            ],
            -1,
        )
        return arms, _vec(self.anchors)[:, :2] - (y[..., None, :2] + arms)

    def derivative(self, t: float, y: np.ndarray) -> np.ndarray:
        arms, d = self.spring_vectors(y)
        length = np.linalg.norm(d, axis=-1)
        force = (_vec(self.stiffnesses) * (length - _vec(self.rest_lengths)) / length)[:, None] * d
        torque = (arms[:, 0] * force[:, 1] - arms[:, 1] * force[:, 0]).sum()
        accel = (force.sum(0) - self.damping * y[3:5]) / self.mass
        spin = torque / self.inertia - self.damping / self.mass * y[5]
        return np.array([*y[3:], *accel, spin])

    def energy(self, y: np.ndarray) -> np.ndarray:
        """[...] kinetic plus spring energy of states [..., 6]."""
        length = np.linalg.norm(self.spring_vectors(y)[1], axis=-1)
        springs = 0.5 * (_vec(self.stiffnesses) * (length - _vec(self.rest_lengths)) ** 2).sum(-1)
        return 0.5 * self.mass * (y[..., 3:5] ** 2).sum(-1) + 0.5 * self.inertia * y[..., 5] ** 2 + springs

    def transform(self, t) -> np.ndarray:
        y = trajectory_of(self)(t)
        R = axis_angle_to_matrix((0.0, 0.0, 1.0), y[..., 2])
        shift = np.concatenate([y[..., :2] - _vec(self.pivot)[:2], np.zeros((*y.shape[:-1], 1))], -1)
        return rigid_transform(R, self.pivot, shift)

    def angular_velocity_at(self, t) -> np.ndarray:
        return trajectory_of(self)(t)[..., 5, None] * np.array([0.0, 0.0, 1.0])

    def record(self) -> dict:
        return {"type": self.kind, **plain(asdict(self))}


INTEGRATED = {cls.kind: cls for cls in (RollingBall, Gyroscope, HingedChain, PlanarSprings)}
"""Record ``type`` -> the dataclass whose fields the record holds."""
