"""Exact trajectories of the synthetic parts whose motion has no closed form: an ODE integrated once
with tight tolerances and evaluated at any time through the integrator's dense output, and the
quaternion algebra the rigid-body ones share.

The state of a mechanism at t = 0 and its constants are its ``gt/motion.json`` record, so the same
numbers always give the same trajectory (the solution is cached per mechanism). The dense output of
an 8th-order Dormand-Prince step (DOP853) at relative tolerance 1e-11 keeps the integrated quantities
(energy, constraint lengths) within about 1e-9 of their exact values over the whole span.

# T: times (any leading shape ...), S: state size
"""

from __future__ import annotations

from collections.abc import Callable
from functools import lru_cache

import numpy as np

T_FIRST, T_LAST = -1.0, 4.0
"""The span a trajectory is integrated over: past the extrapolation horizon both ways."""
RTOL, ATOL = 1e-11, 1e-12


class Trajectory:
    """The solution of y' = f(t, y), y(0) = y0, on [T_FIRST, T_LAST] (integrated from 0 both ways)."""

    def __init__(self, fun: Callable[[float, np.ndarray], np.ndarray], y0: np.ndarray):
        from scipy.integrate import solve_ivp

        y0 = np.asarray(y0, dtype=np.float64)
        solve = lambda end: solve_ivp(  # noqa: E731
            fun, (0.0, end), y0, method="DOP853", rtol=RTOL, atol=ATOL, dense_output=True
        )
        self.forward, self.backward = solve(T_LAST), solve(T_FIRST)
        for part in (self.forward, self.backward):
            if not part.success:
                raise RuntimeError(f"the integration failed: {part.message}")

    def __call__(self, t) -> np.ndarray:
        """[..., S] the state at times ``t`` [...] in [T_FIRST, T_LAST]."""
        t = np.asarray(t, dtype=np.float64)
        if t.size and (t.min() < T_FIRST or t.max() > T_LAST):
            raise ValueError(f"times must lie in [{T_FIRST}, {T_LAST}], got [{t.min()}, {t.max()}]")
        flat = t.reshape(-1)
        out = np.empty((flat.size, self.forward.y.shape[0]))
        ahead = flat >= 0
        if ahead.any():
            out[ahead] = self.forward.sol(flat[ahead]).T
        if (~ahead).any():
            out[~ahead] = self.backward.sol(flat[~ahead]).T
        return out.reshape(*t.shape, -1)


@lru_cache(maxsize=64)
def trajectory_of(mechanism) -> Trajectory:
    """The (cached) trajectory of a hashable ``mechanism`` with ``derivative(t, y)`` and ``initial_state()``."""
    return Trajectory(mechanism.derivative, mechanism.initial_state())


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """[..., 3, 3] rotation of the quaternions ``q`` [..., 4] (w, x, y, z), normalised first."""
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """[4] (w, x, y, z) of the rotation matrix ``R`` [3, 3] (Shepperd's method, any angle)."""
    R = np.asarray(R, dtype=np.float64)
    trace = np.trace(R)
    k = int(np.argmax([trace, R[0, 0], R[1, 1], R[2, 2]]))
    if k == 0:
        s = 2 * np.sqrt(1 + trace)
        q = [s / 4, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    else:
        i, j, m = k - 1, k % 3, (k + 1) % 3
        s = 2 * np.sqrt(1 + R[i, i] - R[j, j] - R[m, m])
        q = [0.0] * 4
        q[0], q[1 + i] = (R[m, j] - R[j, m]) / s, s / 4
        q[1 + j], q[1 + m] = (R[j, i] + R[i, j]) / s, (R[m, i] + R[i, m]) / s
    q = np.asarray(q)
    return q / np.linalg.norm(q)


def quaternion_rate(q: np.ndarray, omega_world: np.ndarray) -> np.ndarray:
    """[4] dq/dt = 1/2 (0, omega) q for a world angular velocity ``omega_world`` [3]."""
    w, v = q[0], q[1:]
    return 0.5 * np.concatenate([[-omega_world @ v], w * omega_world + np.cross(omega_world, v)])
