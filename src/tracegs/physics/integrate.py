"""Time integration of the translation-rotation dynamics of rigid particles (Section 3.2, Alg. 1).

N: particles (Gaussians). All functions are pure functions of tensors and know nothing of networks:
a dynamics field (``models/dynamics.py``) produces a ``DynamicsParams`` once, at (x_t', t'), and the
integrators here carry every particle from t' to t' + dt with it (diffusers-style: the scheme can be
swapped without touching the model).

The motion of a particle at position x [N, 3] is the rigid-body velocity field (Eq. 3-5)

    dx/ds = v_bar(s) + w(s) x x,        dR/ds = [w(s)]_x R,

with the equivalent centre velocity ``v_bar`` and angular velocity ``w`` evolving polynomially in the
time ``s`` elapsed since the query (Alg. 1: params(t' + s) = params(t') + s (a_bar, eps), plus
s^2/2 (jerk) for the third-order system). The position ODE is linear in x with time-varying
coefficients; the orientation obeys the same rotation, so a particle and its Gaussian turn together.
Negative ``dt`` integrates backward in time with the same formulas.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import torch

from tracegs.physics import fused
from tracegs.physics.so3 import (
    axis_angle_to_quat,
    quat_multiply,
    quat_normalize,
    rodrigues,
    rotmat_to_quat,
)

Time = float | torch.Tensor  # a Python scalar, or a tensor broadcastable to [N, 1]


class DynamicsParams(NamedTuple):
    """Per-particle dynamics parameters at the query time (output of f_trd, Eq. 5-6).

    Order 1: accelerations are zeros. Order 2: constant accelerations. Order 3: ``jerk`` and
    ``angular_jerk`` are set and the accelerations themselves evolve linearly.
    """

    velocity: torch.Tensor
    """[N, 3] equivalent centre velocity v_bar = v_c - w x P_c (Eq. 5)."""
    angular_velocity: torch.Tensor
    """[N, 3] angular velocity w (rotation vector rate, right-hand rule)."""
    acceleration: torch.Tensor
    """[N, 3] equivalent centre acceleration a_bar = a_c - eps x P_c (Eq. 5)."""
    angular_acceleration: torch.Tensor
    """[N, 3] angular acceleration eps."""
    jerk: torch.Tensor | None = None
    """[N, 3] equivalent centre jerk (order 3 only)."""
    angular_jerk: torch.Tensor | None = None
    """[N, 3] angular jerk (order 3 only)."""

    @property
    def order(self) -> int:
        """3 with jerk terms, else 2 (order 1 is order 2 with zero accelerations)."""
        return 3 if self.jerk is not None else 2

    def to(self, *args, **kwargs) -> DynamicsParams:
        """All tensors through ``Tensor.to`` (e.g. ``.to(torch.float32)`` after bf16 autocast)."""
        return DynamicsParams(*(None if p is None else p.to(*args, **kwargs) for p in self))


def zero_params(x: torch.Tensor, order: int = 2) -> DynamicsParams:
    """No motion, for particles like ``x`` [N, 3]."""
    zero = torch.zeros_like(x)
    jerk = zero if order >= 3 else None
    return DynamicsParams(zero, zero, zero, zero, jerk, jerk)


def params_at(params: DynamicsParams, s: Time) -> DynamicsParams:
    """The parameters ``s`` after their query time (Alg. 1, RK2 step 1).

    Velocities: ``v(s) = v + s a (+ s^2/2 j)``; accelerations: ``a(s) = a (+ s j)``; jerk constant.
    """
    v, w, a, e, j, n = params
    if j is None:
        return DynamicsParams(v + s * a, w + s * e, a, e)
    return DynamicsParams(
        v + s * a + 0.5 * s * s * j, w + s * e + 0.5 * s * s * n, a + s * j, e + s * n, j, n
    )


def velocities_at(params: DynamicsParams, s: Time) -> tuple[torch.Tensor, torch.Tensor]:
    """``(v_bar(s), w(s))`` [N, 3] each: the velocity part of ``params_at``."""
    evolved = params_at(params, s)
    return evolved.velocity, evolved.angular_velocity


def acceleration_consistency(params: DynamicsParams, later: DynamicsParams, s: float) -> torch.Tensor:
    """Mean L1 gap, in acceleration units, between the velocities ``later`` observed ``s`` after the
    query of ``params`` (e.g. f_trd queried again along the trajectory) and those that ``params``'
    accelerations predict: ``|v + s a - v_later| / |s|`` for ``v_bar`` and ``w``.

    ``params``' velocities and all of ``later`` are held fixed, so the gradient reaches only the
    accelerations (and jerks): they learn the time derivative of the velocity field along the motion.
    Zero when the velocity field changes exactly as the accelerations say (constant-acceleration motion).
    """
    if params.jerk is None:  # (second order: one autograd node, the same arithmetic)
        held = [p.detach() for p in (params.velocity, params.angular_velocity, *later[:2])]
        return fused.second_order_consistency(params.acceleration, params.angular_acceleration, *held, s)
    held = params._replace(
        velocity=params.velocity.detach(), angular_velocity=params.angular_velocity.detach()
    )
    v, w = velocities_at(held, s)
    gap = (v - later.velocity.detach()).abs().mean() + (w - later.angular_velocity.detach()).abs().mean()
    return gap / abs(s)


def params_in_world(params: DynamicsParams, center: torch.Tensor, scale: float) -> DynamicsParams:
    """The same motion in world coordinates ``x = center + scale * x_n``, for ``params`` of particles
    at normalised positions ``x_n`` (the frame the fields see, ``TraceModel.set_field_frame``).

    ``dx/ds = scale (v_n + w x x_n) = (scale v_n - w x center) + w x x``: the equivalent velocity
    becomes ``scale v_n - w x center``, and each higher term the same with its own rotational partner
    (``scale a_n - eps x center``, ``scale j_n - angular_jerk x center``); rotations are unchanged. Both
    frames therefore integrate to the same world trajectories, exactly.
    """

    def world(linear: torch.Tensor | None, angular: torch.Tensor | None) -> torch.Tensor | None:
        if linear is None:
            return None
        return scale * linear - torch.cross(angular, center.to(angular).expand_as(angular), dim=-1)

    v, w, a, e, j, n = params
    return DynamicsParams(world(v, w), w, world(a, e), e, world(j, n), n)


def particle_velocity(
    x: torch.Tensor, velocity: torch.Tensor, angular_velocity: torch.Tensor
) -> torch.Tensor:
    """Velocity of the particle at absolute position ``x`` [N, 3]: ``v_bar + w x x`` (Eq. 3-4)."""
    return velocity + torch.cross(angular_velocity, x, dim=-1)


def equivalent_from_center(
    center: torch.Tensor,
    center_velocity: torch.Tensor,
    center_acceleration: torch.Tensor,
    angular_velocity: torch.Tensor,
    angular_acceleration: torch.Tensor,
    center_jerk: torch.Tensor | None = None,
    angular_jerk: torch.Tensor | None = None,
) -> DynamicsParams:
    """Equivalent parameters of a rotation about an explicit centre P_c (Eq. 5, Appendix).

    ``v_bar = v_c - w x P_c`` and ``a_bar = a_c - eps x P_c``; the Appendix proves that the composite
    velocity ``w x (P - P_c) + v_c`` is then reproduced at t and t + dt. The same identity gives the
    third-order term ``j_bar = j_c - angular_jerk x P_c``. All tensors [N, 3]. Used by the
    "no equivalent parametrisation" ablation, so that it is integrated by exactly the same code.
    """
    velocity = center_velocity - torch.cross(angular_velocity, center, dim=-1)
    acceleration = center_acceleration - torch.cross(angular_acceleration, center, dim=-1)
    if center_jerk is None:
        return DynamicsParams(velocity, angular_velocity, acceleration, angular_acceleration)
    jerk = center_jerk - torch.cross(angular_jerk, center, dim=-1)
    return DynamicsParams(velocity, angular_velocity, acceleration, angular_acceleration, jerk, angular_jerk)


# ---------------------------------------------------------------------------------------------------
# Schemes. Each maps (x [N, 3], params, dt) to (x_new [N, 3], rotation vector [N, 3] of the step's
# rotation increment dR, applied on the left: R_new = dR R). Their orders are measured by the tests
# on closed-form motions and reported in docs/PHYSICS.md.


def euler_scheme(x: torch.Tensor, params: DynamicsParams, dt: Time) -> tuple[torch.Tensor, torch.Tensor]:
    """Explicit Euler: ``x + dt v(x; params(0))``, ``dR = Rodrigues(dt w(0))``. First order."""
    v, w = params.velocity, params.angular_velocity
    return x + dt * particle_velocity(x, v, w), dt * w


def rk2_scheme(x: torch.Tensor, params: DynamicsParams, dt: Time) -> tuple[torch.Tensor, torch.Tensor]:
    """Explicit midpoint RK2 as in the authors' code (Alg. 1, RK2 steps 2-4). Second order.

    ``x_mid = x + dt/2 v(x; params(0))``, ``x_new = x + dt (v_bar_mid + w_mid x x_mid)``,
    ``dR = Rodrigues(dt w_mid)`` (the midpoint rule for the rotation, i.e. 2nd-order Magnus).
    """
    x_mid = x + 0.5 * dt * particle_velocity(x, params.velocity, params.angular_velocity)
    v_mid, w_mid = velocities_at(params, 0.5 * dt)
    return x + dt * particle_velocity(x_mid, v_mid, w_mid), dt * w_mid


def rk2_paper_scheme(x: torch.Tensor, params: DynamicsParams, dt: Time) -> tuple[torch.Tensor, torch.Tensor]:
    """Algorithm 1 taken literally: ``x_new = x + dt (v_bar_mid + w_mid x x_t')``.

    The rotational part of the velocity is evaluated at the start point, so the term
    ``dt^2/2 w x (v_bar + w x x)`` of the Taylor expansion is missing: second order for a pure
    translation (exact under constant acceleration), first order as soon as particles rotate.
    The orientation update is the same as ``rk2_scheme``.
    """
    v_mid, w_mid = velocities_at(params, 0.5 * dt)
    return x + dt * particle_velocity(x, v_mid, w_mid), dt * w_mid


def rk4_scheme(x: torch.Tensor, params: DynamicsParams, dt: Time) -> tuple[torch.Tensor, torch.Tensor]:
    """Classic RK4 on ``dx/ds = v_bar(s) + w(s) x x``; 4th-order Magnus for the rotation.

    The rotation increment uses the two-point Gauss-Legendre Magnus expansion
    ``Omega = dt/2 (w1 + w2) + sqrt(3)/12 dt^2 (w2 x w1)``, ``w_i = w(c_i dt)``,
    ``c_{1,2} = 1/2 -/+ sqrt(3)/6`` (the commutator of two cross-product matrices is the cross-product
    matrix of the cross product), so position and orientation are both fourth order.
    """

    def f(y: torch.Tensor, s: Time) -> torch.Tensor:
        return particle_velocity(y, *velocities_at(params, s))

    half = 0.5 * dt
    k1 = f(x, 0.0)
    k2 = f(x + half * k1, half)
    k3 = f(x + half * k2, half)
    k4 = f(x + dt * k3, dt)
    x_new = x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    c = math.sqrt(3) / 6
    _, w1 = velocities_at(params, (0.5 - c) * dt)
    _, w2 = velocities_at(params, (0.5 + c) * dt)
    rotvec = half * (w1 + w2) + (math.sqrt(3) / 12) * dt * dt * torch.cross(w2, w1, dim=-1)
    return x_new, rotvec


Scheme = Callable[[torch.Tensor, DynamicsParams, Time], tuple[torch.Tensor, torch.Tensor]]

SCHEMES: dict[str, Scheme] = {
    "euler": euler_scheme,
    "rk2": rk2_scheme,
    "rk2_paper": rk2_paper_scheme,
    "rk4": rk4_scheme,
}
"""Integrators by name; ``"rk2"`` (midpoint, authors' code) is the default everywhere."""


def rotate(rotation: torch.Tensor, rotvec: torch.Tensor) -> torch.Tensor:
    """Unit quaternion [N, 4] of ``Rodrigues(rotvec) @ R`` (Alg. 1: R_t = dR R_t').

    ``rotation`` is a quaternion [N, 4] (composed as ``dq o q``, the same rotation without a matrix
    round trip, and keeping the quaternion's sign continuous along a trajectory) or a rotation
    matrix [N, 3, 3] (the paper's literal path: matrix product, then matrix -> quaternion with w >= 0).
    """
    if rotation.shape[-2:] == (3, 3):
        return rotmat_to_quat(rodrigues(rotvec) @ rotation)
    return quat_normalize(quat_multiply(axis_angle_to_quat(rotvec), rotation))


def step(
    x: torch.Tensor,  # [N, 3] positions at t'
    rotation: torch.Tensor | None,  # [N, 4] quaternions (wxyz) or [N, 3, 3] rotation matrices at t'
    params: DynamicsParams,  # the dynamics at t' (each [N, 3])
    dt: Time,  # signed step; negative integrates backward
    method: str = "rk2",
) -> tuple[torch.Tensor, torch.Tensor | None, DynamicsParams]:
    """One step of Alg. 1 (or another scheme): ``(x_t, q_t [N, 4] unit, params(t' + dt))``.

    Scales are not touched: each Gaussian is a rigid particle (Alg. 1, last line). With
    ``rotation=None`` only the positions move (``q_t`` is None): the orientation update is most
    of a step's cost and does not change the positions.
    """
    x_new, rotvec = SCHEMES[method](x, params, dt)
    rotation = None if rotation is None else rotate(rotation, rotvec)
    return x_new, rotation, params_at(params, dt)


def num_substeps(dt_total: float, dt_max: float) -> int:
    """``ceil(|dt_total| / dt_max)``, tolerant to round-off (2/60 over 1/60 is 2 steps, not 3)."""
    if dt_max <= 0:
        raise ValueError(f"dt_max must be positive, got {dt_max}")
    ratio = abs(dt_total) / dt_max
    return max(1, math.ceil(ratio - 1e-9 * max(1.0, ratio)))


def integrate(
    x: torch.Tensor,  # [N, 3]
    q: torch.Tensor | None,  # [N, 4] (or [N, 3, 3]); None: positions only
    params: DynamicsParams,  # at the start time
    dt_total: float,  # signed duration
    dt_max: float,  # largest sub-step magnitude (e.g. 1 / fps)
    method: str = "rk2",
) -> tuple[torch.Tensor, torch.Tensor | None, DynamicsParams]:
    """Chain ``n = ceil(|dt_total| / dt_max)`` equal steps from t' to t' + dt_total.

    The parameters are queried once, at the start, and evolve between sub-steps with
    ``params_at``. Forward (``dt_total > 0``) or backward (``< 0``); ``dt_total == 0`` returns the
    inputs unchanged. Returns ``(x, q, params)`` at the end time.
    """
    dt_total = float(dt_total)
    if dt_total == 0.0:
        return x, q, params
    native = _native_rk2(x, q, params, dt_total, dt_max, method)
    if native is not None:
        return *native, params_at(params, dt_total)
    return _substeps(x, q, params, dt_total, dt_max, method)


def _substeps(x, q, params: DynamicsParams, dt_total: float, dt_max: float, method: str):
    """``integrate``'s PyTorch path: its ``n`` equal steps, one ``step`` each."""
    n = num_substeps(dt_total, dt_max)
    dt = dt_total / n
    for _ in range(n):
        x, q, params = step(x, q, params, dt, method)
    return x, q, params


def integrate_states(
    x: torch.Tensor,
    q: torch.Tensor | None,
    params: DynamicsParams,
    dt_total: float,
    dt_max: float,
    method: str = "rk2",
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """``integrate``'s ``(x, q)`` alone: on the native RK2's path without the parameters at the end
    time (a training step reads only where the particles went)."""
    dt_total = float(dt_total)
    if dt_total == 0.0:
        return x, q
    native = _native_rk2(x, q, params, dt_total, dt_max, method)
    return native if native is not None else _substeps(x, q, params, dt_total, dt_max, method)[:2]


def integrate_rows(
    x: torch.Tensor,
    q: torch.Tensor,
    rows: torch.Tensor | None,
    params: DynamicsParams,
    dt_total: float,
    dt_max: float,
    method: str = "rk2",
    straight_through: bool = False,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``integrate_states`` of the rows ``rows`` (distinct indices; all where None) of ``x`` [N, 3] and
    ``q`` [N, 4], ``params`` given for those rows: ``(x, q)`` [N, ...] with the rows moved and the
    others kept, and the moved rows' positions [M, 3] (without gradient). ``straight_through``: the
    motion starts from ``x`` detached and the positions' gradient passes to ``x`` unchanged (a TRACE
    training step: f_defo's gradient reaches the rendered position). On the native RK2's path the
    gathers and copies back are inside its op (``fused.fused_rk2_rows``)."""
    dt_total = float(dt_total)
    if rows is not None and method == "rk2" and dt_total != 0.0:
        n = num_substeps(dt_total, dt_max)
        if fused.applies_rows(x, q, rows, params, n):
            return fused.fused_rk2_rows(x, q, rows, params, dt_total / n, n, straight_through)
    start = x.detach() if straight_through else x
    x_run, q_run = (start, q) if rows is None else (start[rows], q[rows])
    moved, q_moved = integrate_states(x_run, q_run, params, dt_total, dt_max, method)
    x_out, q_out = (
        (moved, q_moved)
        if rows is None
        else (start.index_copy(0, rows, moved), q.index_copy(0, rows, q_moved))
    )
    if straight_through:
        x_out = x_out + (x - x.detach())
    return x_out, q_out, moved.detach()


def _native_rk2(x, q, params, dt_total: float, dt_max: float, method: str):
    """``(x, q)`` by the native RK2 (the same sub-steps as one op) where it applies (rk2, quaternions or
    positions only; a nonzero duration), else None."""
    if method != "rk2":
        return None
    n = num_substeps(dt_total, dt_max)
    return fused.fused_rk2(x, q, params, dt_total / n, n) if fused.applies(x, q, params, n) else None


ParamsFn = Callable[[torch.Tensor, float], DynamicsParams]


def integrate_field(
    params_fn: ParamsFn,  # (x [N, 3], t) -> DynamicsParams, e.g. a DynamicsField
    x: torch.Tensor,  # [N, 3]
    q: torch.Tensor,  # [N, 4] (or [N, 3, 3])
    t_start: float,
    dt_total: float,
    dt_max: float,
    method: str = "rk2",
) -> tuple[torch.Tensor, torch.Tensor]:
    """Chain steps of Alg. 1, re-querying the dynamics at the start of every sub-step.

    This is Alg. 1 applied repeatedly (each application begins with ``f_trd(x_t', t')``), the
    alternative to ``integrate``'s single query; the integrator still only sees a callable.
    """
    dt_total = float(dt_total)
    if dt_total == 0.0:
        return x, q
    n = num_substeps(dt_total, dt_max)
    dt = dt_total / n
    for i in range(n):
        x, q, _ = step(x, q, params_fn(x, t_start + i * dt), dt, method)
    return x, q
