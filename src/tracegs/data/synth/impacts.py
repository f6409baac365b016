"""An impact between two moving parts, in closed form: two discs sliding on a table under dry friction,
one striking the other, both moving after it.

Between contacts each disc slides in a straight line with the constant deceleration ``deceleration``
(mu g) against its velocity until it stops; at the contact (the centres 2 r apart, found to machine
precision) an impulse along the line of centres (smooth discs: no tangential impulse, no spin)
conserves momentum and scales the normal relative velocity by -``restitution``.

# T: times (any leading shape ...)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import cached_property

import numpy as np

from .kinematics import plain, rigid_transform

FORMULAS = {
    "sliding_collision": (
        "two discs of radius r on a table: each slides as p(t) = p0 + u (s tau - d tau^2 / 2), tau = "
        "min(t, s / d), u = v0 / s, s = |v0|, d = deceleration; at the first contact time (|pA - pB| = 2 r) "
        "J = (1 + e) ((vA - vB) . n) / (1 / mA + 1 / mB), n = (pB - pA) / 2r, vA -= J n / mA, vB += J n / mB, "
        "and both slide on from there; x(t) = x0 + p(t) - p(0) for the disc ``puck``"
    ),
}


def slide(position, velocity, deceleration: float, t) -> tuple[np.ndarray, np.ndarray]:
    """(position [..., 3], velocity [..., 3]) of a disc sliding from ``position`` at ``velocity`` for
    times ``t`` [...] (>= 0: it stops at |v| / deceleration; < 0: the same motion backwards in time)."""
    t = np.asarray(t, dtype=np.float64)
    p, v = np.asarray(position, dtype=np.float64), np.asarray(velocity, dtype=np.float64)
    speed = float(np.linalg.norm(v))
    if speed == 0.0:
        return np.broadcast_to(p, (*t.shape, 3)).copy(), np.zeros((*t.shape, 3))
    u = v / speed
    tau = np.minimum(t, speed / deceleration)[..., None]
    return p + u * (speed * tau - 0.5 * deceleration * tau**2), u * (speed - deceleration * tau)


@dataclass(frozen=True)
class SlidingCollision:
    """Disc ``puck`` (0: the striker, 1: the one struck) of two sliding discs that collide once."""

    centers: tuple[tuple[float, float, float], ...] = ((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    """Both discs' centres at t = 0 (at the same height)."""
    velocities: tuple[tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    """Both discs' horizontal velocities at t = 0."""
    radius: float = 0.1
    masses: tuple[float, float] = (1.0, 1.0)
    restitution: float = 0.8
    deceleration: float = 0.5
    """mu g: the friction's deceleration of a sliding disc."""
    puck: int = 0
    kind = "sliding_collision"

    def __post_init__(self):
        for name in ("centers", "velocities"):  # json lists of lists: hashable again
            object.__setattr__(self, name, tuple(tuple(float(x) for x in p) for p in getattr(self, name)))
        gap = np.linalg.norm(np.subtract(self.centers[1], self.centers[0]))
        checks = [
            (len(self.centers) == len(self.velocities) == len(self.masses) == 2, "two discs"),
            (self.puck in (0, 1), "puck 0 or 1"),
            (self.radius > 0 and gap > 2 * self.radius, "discs of radius > 0 apart at t = 0"),
            (min(self.masses) > 0 and self.deceleration > 0, "masses and deceleration > 0"),
            (0 <= self.restitution <= 1, "restitution in [0, 1]"),
            (abs(self.centers[0][2] - self.centers[1][2]) < 1e-12, "both centres at one height"),
        ]
        for ok, what in checks:
            if not ok:
                raise ValueError(f"a sliding collision needs {what}, got {self}")
        if not np.isfinite(self.contact_time):
            raise ValueError(f"the discs never touch: {self}")

    def _before(self, t) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
        return tuple(
            slide(p, v, self.deceleration, t) for p, v in zip(self.centers, self.velocities, strict=True)
        )

    @cached_property
    def contact_time(self) -> float:
        """The first time > 0 at which the centres are 2 r apart (inf when never, before both stop)."""
        from scipy.optimize import brentq

        stop = max(np.linalg.norm(v) for v in self.velocities) / self.deceleration
        grid = np.linspace(0.0, stop, 4001)
        (a, _), (b, _) = self._before(grid)
        gap = np.linalg.norm(a - b, axis=-1) - 2 * self.radius
        inside = np.flatnonzero(gap <= 0)
        if not len(inside):
            return float("inf")
        k = int(inside[0])

        def gap_at(s: float) -> float:
            (a, _), (b, _) = self._before(s)
            return float(np.linalg.norm(a - b)) - 2 * self.radius

        return float(brentq(gap_at, grid[k - 1], grid[k], xtol=1e-15, rtol=4 * np.finfo(float).eps))

    @cached_property
    def after(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(positions [2, 3], velocities [2, 3] right after the impact, impulse J, normal n [3])."""
        (pa, va), (pb, vb) = self._before(self.contact_time)
        n = (pb - pa) / np.linalg.norm(pb - pa)
        ma, mb = self.masses
        impulse = (1 + self.restitution) * float((va - vb) @ n) / (1 / ma + 1 / mb)
        return np.stack([pa, pb]), np.stack([va - impulse / ma * n, vb + impulse / mb * n]), impulse, n

    def path(self, t) -> tuple[np.ndarray, np.ndarray]:
        """(centre [..., 3], velocity [..., 3]) of disc ``puck`` at times ``t`` [...]."""
        t = np.asarray(t, dtype=np.float64)
        p, v = self._before(t)[self.puck]
        positions, velocities, _, _ = self.after
        q, w = slide(positions[self.puck], velocities[self.puck], self.deceleration, t - self.contact_time)
        later = (t > self.contact_time)[..., None]
        return np.where(later, q, p), np.where(later, w, v)

    def transform(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        start = np.asarray(self.centers[self.puck])
        return rigid_transform(np.broadcast_to(np.eye(3), (*t.shape, 3, 3)), start, self.path(t)[0] - start)

    def angular_velocity_at(self, t) -> np.ndarray:
        return np.zeros((*np.shape(t), 3))

    def record(self) -> dict:
        _, velocities, impulse, _ = self.after
        stops = [self.contact_time + float(np.linalg.norm(v)) / self.deceleration for v in velocities]
        return {
            "type": self.kind,
            **plain(asdict(self)),
            "contact_time": self.contact_time,
            "velocities_after": velocities.tolist(),
            "impulse": impulse,
            "stop_times": stops,
        }
