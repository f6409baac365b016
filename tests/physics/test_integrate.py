"""Integrators against closed-form rigid motions: exactness, convergence orders, reversibility, grads."""

import math

import pytest
import torch

from tracegs.physics.integrate import (
    SCHEMES,
    DynamicsParams,
    acceleration_consistency,
    equivalent_from_center,
    integrate,
    integrate_field,
    num_substeps,
    params_at,
    params_in_world,
    particle_velocity,
    step,
    zero_params,
)
from tracegs.physics.so3 import (
    axis_angle_to_quat,
    quat_canonical,
    quat_multiply,
    quat_normalize,
    quat_to_axis_angle,
    quat_to_rotmat,
    rodrigues,
)

f64 = torch.float64
N = 16
T = 1.0


def randn(*shape, seed: int) -> torch.Tensor:
    return torch.randn(*shape, generator=torch.Generator().manual_seed(seed), dtype=f64)


def unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def start_state() -> tuple[torch.Tensor, torch.Tensor]:
    return randn(N, 3, seed=0), quat_normalize(randn(N, 4, seed=1))


def rotation_error(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Angle [N] of the relative rotation q1 q2^-1."""
    q2_inv = q2 * q2.new_tensor([1.0, -1.0, -1.0, -1.0])
    return quat_to_axis_angle(quat_multiply(q1, q2_inv)).norm(dim=-1)


# ---------------------------------------------------------------------------------------------------
# Closed-form motions. Each returns (params at t = 0, exact (x, q) at time t as a function).


def pivot_rotation():
    """(a) Constant angular velocity about an off-origin axis through a pivot p: v_bar = -w x p."""
    w, p = 1.7 * unit(randn(N, 3, seed=2)), randn(N, 3, seed=3)
    params = equivalent_from_center(p, torch.zeros_like(p), torch.zeros_like(p), w, torch.zeros_like(p))

    def exact(x0, q0, t):
        return p + (rodrigues(w * t) @ (x0 - p)[..., None])[..., 0], quat_multiply(
            axis_angle_to_quat(w * t), q0
        )

    return params, exact


def constant_acceleration():
    """(b) Translation under constant acceleration: x0 + v t + a t^2 / 2."""
    v, a = randn(N, 3, seed=4), randn(N, 3, seed=5)
    zero = torch.zeros_like(v)
    params = DynamicsParams(v, zero, a, zero)
    return params, lambda x0, q0, t: (x0 + v * t + 0.5 * a * t * t, q0)


def accelerated_screw():
    """(c) Rotation with angular acceleration about a fixed axis n through a pivot c0 that itself
    accelerates along n: angle w0 t + eps t^2 / 2, pivot c0 + u t + b t^2 / 2 (u, b parallel to n).
    Then v_bar(t) = u(t) - w(t) x c0 is linear in t, i.e. exactly the dynamics system of Eq. 5."""
    n = unit(randn(N, 3, seed=6))
    w0, alpha = 1.5 * randn(N, 1, seed=7), randn(N, 1, seed=8)
    c0, u, b = randn(N, 3, seed=9), randn(N, 1, seed=10) * n, randn(N, 1, seed=11) * n
    params = equivalent_from_center(c0, u, b, w0 * n, alpha * n)

    def exact(x0, q0, t):
        rotvec = (w0 * t + 0.5 * alpha * t * t) * n
        center = c0 + u * t + 0.5 * b * t * t
        return center + (rodrigues(rotvec) @ (x0 - c0)[..., None])[..., 0], quat_multiply(
            axis_angle_to_quat(rotvec), q0
        )

    return params, exact


def jerk_translation():
    """Order 3 translation: x0 + v t + a t^2/2 + j t^3/6."""
    v, a, j = randn(N, 3, seed=12), randn(N, 3, seed=13), randn(N, 3, seed=14)
    zero = torch.zeros_like(v)
    params = DynamicsParams(v, zero, a, zero, j, zero)
    return params, lambda x0, q0, t: (x0 + v * t + a * t * t / 2 + j * t**3 / 6, q0)


def spinning_projectile(order: int = 3):
    """A body spinning at constant w about its own centre, which flies under a constant acceleration
    a not along w (a ball thrown with spin): c(t) = c0 + v t + a t^2 / 2. Its equivalent velocity
    v_bar(t) = c'(t) - w x c(t) is quadratic in t, so Eq. 5 needs the third-order term: a_bar =
    a - w x v, jerk = -w x a. ``order=2`` drops that term (what the second-order system can hold)."""
    w, c0 = 1.7 * unit(randn(N, 3, seed=15)), randn(N, 3, seed=16)
    v, a = randn(N, 3, seed=17), randn(N, 3, seed=18)
    zero = torch.zeros_like(v)
    jerk = (-torch.linalg.cross(w, a), zero) if order == 3 else ()
    params = DynamicsParams(v - torch.linalg.cross(w, c0), w, a - torch.linalg.cross(w, v), zero, *jerk)

    def exact(x0, q0, t):
        center = c0 + v * t + 0.5 * a * t * t
        return center + (rodrigues(w * t) @ (x0 - c0)[..., None])[..., 0], quat_multiply(
            axis_angle_to_quat(w * t), q0
        )

    return params, exact


MOTIONS = {
    "pivot_rotation": pivot_rotation,
    "constant_acceleration": constant_acceleration,
    "accelerated_screw": accelerated_screw,
    "jerk_translation": jerk_translation,
    "spinning_projectile": spinning_projectile,
}


def errors(motion: str, method: str, n_steps: int) -> tuple[float, float]:
    params, exact = MOTIONS[motion]()
    x0, q0 = start_state()
    x, q, _ = integrate(x0, q0, params, T, T / n_steps, method)
    x_ref, q_ref = exact(x0, q0, T)
    return (x - x_ref).norm(dim=-1).max().item(), rotation_error(q, q_ref).max().item()


# (motion, method): (order of the position error, order of the orientation error); None = exact
EXPECTED_ORDERS = {
    ("pivot_rotation", "euler"): (1, None),
    ("pivot_rotation", "rk2"): (2, None),
    ("pivot_rotation", "rk2_paper"): (1, None),
    ("pivot_rotation", "rk4"): (4, None),
    ("constant_acceleration", "euler"): (1, None),
    ("constant_acceleration", "rk2"): (None, None),
    ("constant_acceleration", "rk2_paper"): (None, None),
    ("constant_acceleration", "rk4"): (None, None),
    ("accelerated_screw", "euler"): (1, 1),
    ("accelerated_screw", "rk2"): (2, None),
    ("accelerated_screw", "rk2_paper"): (1, None),
    ("accelerated_screw", "rk4"): (4, None),
    ("jerk_translation", "euler"): (1, None),
    ("jerk_translation", "rk2"): (2, None),
    ("jerk_translation", "rk4"): (None, None),
    ("spinning_projectile", "euler"): (1, None),
    ("spinning_projectile", "rk2"): (2, None),
    ("spinning_projectile", "rk2_paper"): (1, None),
    ("spinning_projectile", "rk4"): (4, None),
}


def assert_order(errs: list[float], order: int | None, what: str) -> None:
    if order is None:
        assert max(errs) < 1e-12, f"{what}: expected exact, errors {errs}"
        return
    ratios = [e1 / e2 for e1, e2 in zip(errs[:-1], errs[1:], strict=True)]
    for r in ratios:
        assert 0.8 * 2**order < r < 1.25 * 2**order, f"{what}: expected order {order}, ratios {ratios}"


@pytest.mark.parametrize(("motion", "method"), sorted(EXPECTED_ORDERS))
def test_convergence_order_on_closed_form_motions(motion, method):
    steps = [16, 32, 64] if method != "rk4" else [8, 16, 32]
    errs = [errors(motion, method, n) for n in steps]
    position_order, orientation_order = EXPECTED_ORDERS[(motion, method)]
    assert_order([e[0] for e in errs], position_order, f"{motion}/{method} position")
    assert_order([e[1] for e in errs], orientation_order, f"{motion}/{method} orientation")


def varying_axis_params() -> DynamicsParams:
    """Angular acceleration not parallel to w: the rotation axis turns, no closed form."""
    return DynamicsParams(
        randn(N, 3, seed=20), 1.5 * randn(N, 3, seed=21), randn(N, 3, seed=22), randn(N, 3, seed=23)
    )


@pytest.mark.parametrize(("method", "position_order", "orientation_order"), [
    ("euler", 1, 1), ("rk2", 2, 2), ("rk2_paper", 1, 2), ("rk4", 4, 4),
])  # fmt: skip
def test_convergence_order_with_turning_axis(method, position_order, orientation_order):
    params = varying_axis_params()
    x0, q0 = start_state()
    x_ref, q_ref, _ = integrate(x0, q0, params, T, T / 1024, "rk4")  # error ~1e-13
    errs = []
    for n in [8, 16, 32] if method == "rk4" else [16, 32, 64]:
        x, q, _ = integrate(x0, q0, params, T, T / n, method)
        errs.append(((x - x_ref).norm(dim=-1).max().item(), rotation_error(q, q_ref).max().item()))
    assert_order([e[0] for e in errs], position_order, f"{method} position")
    assert_order([e[1] for e in errs], orientation_order, f"{method} orientation")


@pytest.mark.parametrize("method", sorted(SCHEMES))
def test_zero_velocity_is_identity(method):
    x0, q0 = start_state()
    x, q, params = integrate(x0, q0, zero_params(x0), 0.7, 0.1, method)
    torch.testing.assert_close(x, x0, atol=0, rtol=0)
    torch.testing.assert_close(q, q0)
    assert all((p == 0).all() for p in params if p is not None)


def test_zero_duration_returns_inputs():
    x0, q0 = start_state()
    params, _ = accelerated_screw()
    x, q, p = integrate(x0, q0, params, 0.0, 0.1)
    assert x is x0 and q is q0 and p is params


@pytest.mark.parametrize("method", sorted(SCHEMES))
def test_forward_then_backward_returns_to_start(method):
    x0, q0 = start_state()
    params, _ = constant_acceleration()
    x1, q1, p1 = integrate(x0, q0, params, T, T / 10, method)
    x2, q2, p2 = integrate(x1, q1, p1, -T, T / 10, method)
    torch.testing.assert_close(p2.velocity, params.velocity)
    if method != "euler":  # exact for translation under constant acceleration
        torch.testing.assert_close(x2, x0, atol=1e-12, rtol=0)
    # with rotation: back to the start to the scheme's accuracy, better with smaller steps
    params, _ = accelerated_screw()
    gaps, turns = [], []
    for n in (16, 32):
        x1, q1, p1 = integrate(x0, q0, params, T, T / n, method)
        x2, q2, _ = integrate(x1, q1, p1, -T, T / n, method)
        gaps.append((x2 - x0).norm(dim=-1).max().item())
        turns.append(rotation_error(q2, q0).max().item())
    assert gaps[1] < gaps[0] / 1.5
    assert turns[1] < max(turns[0] / 1.5, 1e-12)
    assert gaps[1] < {"euler": 2.0, "rk2_paper": 2.0, "rk2": 0.05, "rk4": 1e-5}[method]


def test_backward_matches_closed_form():
    params, exact = accelerated_screw()
    x0, q0 = start_state()
    x, q, _ = integrate(x0, q0, params, -0.5, 0.5 / 200, "rk4")
    x_ref, q_ref = exact(x0, q0, -0.5)
    torch.testing.assert_close(x, x_ref, atol=1e-10, rtol=0)
    assert rotation_error(q, q_ref).max() < 1e-10


def test_chained_integrate_equals_manual_loop():
    x0, q0 = start_state()
    params = varying_axis_params()
    assert num_substeps(2 / 60, 1 / 60) == 2 and num_substeps(0.05, 1 / 60) == 3
    x, q, p = integrate(x0, q0, params, -0.05, 1 / 60, "rk2")  # 3 equal steps of -1/60
    xm, qm, pm = x0, q0, params
    for _ in range(3):
        xm, qm, pm = step(xm, qm, pm, -0.05 / 3, "rk2")
    # (integrate runs rk2 natively where it can: the same operations, rounded in another order)
    torch.testing.assert_close(x, xm, atol=1e-14, rtol=1e-14)
    torch.testing.assert_close(q, qm, atol=1e-14, rtol=1e-14)
    torch.testing.assert_close(p.angular_velocity, params_at(params, -0.05).angular_velocity)


def test_positions_alone_move_as_with_the_orientations():
    x0, q0 = start_state()
    params = varying_axis_params()
    for method in SCHEMES:
        x, q, p = integrate(x0, q0, params, -0.05, 1 / 60, method)
        x_alone, q_alone, p_alone = integrate(x0, None, params, -0.05, 1 / 60, method)
        assert q_alone is None and q is not None
        torch.testing.assert_close(x_alone, x, atol=0, rtol=0)
        torch.testing.assert_close(p_alone.velocity, p.velocity, atol=0, rtol=0)


def test_quaternions_stay_unit_over_long_chains():
    x0, q0 = start_state()
    params = varying_axis_params().to(torch.float32)
    x, q = x0.float(), q0.float()
    for _ in range(2000):
        x, q, _ = step(x, q, params, 1e-3)
    assert (q.norm(dim=-1) - 1).abs().max() < 1e-6
    assert torch.isfinite(x).all()


def test_matrix_and_quaternion_paths_agree():
    x0, q0 = start_state()
    params = varying_axis_params()
    for method in SCHEMES:
        x_q, q_q, _ = step(x0, q0, params, 0.1, method)
        x_r, q_r, _ = step(x0, quat_to_rotmat(q0), params, 0.1, method)
        torch.testing.assert_close(x_r, x_q)
        torch.testing.assert_close(quat_canonical(q_r), quat_canonical(q_q))


def test_rk2_step_is_algorithm_1():
    """One rk2 / rk2_paper step written out with the paper's matrices (Alg. 1)."""
    x0, q0 = start_state()
    v, w, a, e = varying_axis_params()[:4]
    dt = 0.05
    v_mid, w_mid = v + dt / 2 * a, w + dt / 2 * e
    x_mid = x0 + dt / 2 * particle_velocity(x0, v, w)
    theta = dt * w_mid.norm(dim=-1)[:, None, None]
    k1, k2, k3 = (w_mid / w_mid.norm(dim=-1, keepdim=True)).unbind(-1)
    zero = torch.zeros_like(k1)
    K = torch.stack([zero, -k3, k2, k3, zero, -k1, -k2, k1, zero], dim=-1).reshape(N, 3, 3)
    dR = torch.eye(3, dtype=f64) + torch.sin(theta) * K + (1 - torch.cos(theta)) * K @ K
    R_expected = dR @ quat_to_rotmat(q0)
    for method, x_at in (("rk2", x_mid), ("rk2_paper", x0)):
        x, q, _ = step(x0, q0, DynamicsParams(v, w, a, e), dt, method)
        torch.testing.assert_close(x, x0 + dt * (v_mid + torch.linalg.cross(w_mid, x_at)))
        torch.testing.assert_close(quat_to_rotmat(q), R_expected)


def test_equivalent_parametrisation_reproduces_composite_velocity():
    """Appendix: w x (P - P_c) + v_c equals w x P + v_bar at t and t + s (Eq. 3-5)."""
    P, Pc, vc, ac, w, e = (randn(N, 3, seed=s) for s in range(30, 36))
    params = equivalent_from_center(Pc, vc, ac, w, e)
    for s in (0.0, 0.3, -0.2):
        v_bar, w_s = params_at(params, s).velocity, params_at(params, s).angular_velocity
        composite = torch.linalg.cross(w + s * e, P - Pc) + vc + s * ac
        torch.testing.assert_close(particle_velocity(P, v_bar, w_s), composite)


@pytest.mark.parametrize("method", ["rk2", "rk4", "euler"])
@pytest.mark.parametrize("order", [2, 3])
def test_params_in_world_integrate_to_the_mapped_trajectories(method, order):
    """Particles integrated in a normalised frame x_n and mapped to x = c + s x_n land where the
    same particles integrated in the world with ``params_in_world`` land, forward and backward,
    and turn the same."""
    xn, v, w, a, e, j, n = (randn(N, 3, seed=s) for s in range(40, 47))
    q = quat_normalize(randn(N, 4, seed=47))
    params_n = DynamicsParams(v, w, a, e, *((j, n) if order == 3 else ()))
    center, scale = torch.tensor([50.0, -20.0, 3.0], dtype=f64), 7.3
    params_w = params_in_world(params_n, center, scale)
    torch.testing.assert_close(params_w.angular_velocity, w)
    for dt in (0.4, -0.25):
        x_end_n, q_end_n, _ = integrate(xn, q, params_n, dt, 0.05, method)
        x_end_w, q_end_w, _ = integrate(center + scale * xn, q, params_w, dt, 0.05, method)
        torch.testing.assert_close(x_end_w, center + scale * x_end_n)
        torch.testing.assert_close(q_end_w, q_end_n)


def test_integrate_field_requeries_the_field():
    params, exact = pivot_rotation()  # a stationary velocity field: re-querying changes nothing
    x0, q0 = start_state()
    calls = []

    def field(x, t):
        calls.append(t)
        return DynamicsParams(
            params.velocity, params.angular_velocity, params.acceleration, params.acceleration
        )

    x, q = integrate_field(field, x0, q0, 0.2, 0.3, 0.1, "rk4")
    x_ref, q_ref, _ = integrate(x0, q0, params, 0.3, 0.1, "rk4")
    assert calls == pytest.approx([0.2, 0.3, 0.4])
    torch.testing.assert_close(x, x_ref)
    torch.testing.assert_close(q, q_ref)


@pytest.mark.parametrize("method", sorted(SCHEMES))
@pytest.mark.parametrize("order", [2, 3])
def test_gradients_match_finite_differences(method, order):
    n = 3
    x, q = randn(n, 3, seed=40), quat_normalize(randn(n, 4, seed=41))
    terms = [0.5 * randn(n, 3, seed=42 + i) for i in range(2 * order)]
    inputs = tuple(t.requires_grad_(True) for t in (x, q, *terms))

    def run(x, q, *p):
        x1, q1, p1 = integrate(x, q, DynamicsParams(*p), 0.3, 0.1, method)
        return x1, q1, p1.velocity

    assert torch.autograd.gradcheck(run, inputs)


def test_follows_input_dtype_and_time_tensor():
    x0, q0 = start_state()
    params = varying_axis_params().to(torch.float32)
    x, q, p = step(x0.float(), q0.float(), params, torch.full((N, 1), 0.1), "rk2")
    assert x.dtype == q.dtype == p.velocity.dtype == torch.float32
    x_s, q_s, _ = step(x0.float(), q0.float(), params, 0.1, "rk2")
    torch.testing.assert_close(x, x_s)


def test_rk2_is_exact_for_rotation_angle_with_constant_angular_acceleration():
    # fixed axis: w_mid dt is the exact angle increment, whatever the step
    params, exact = accelerated_screw()
    x0, q0 = start_state()
    _, q, _ = integrate(x0, q0, params, T, T / 3, "rk2")
    assert rotation_error(q, exact(x0, q0, T)[1]).max() < 1e-12
    assert math.isfinite(q.sum().item())


@pytest.mark.parametrize("order", [2, 3])
def test_acceleration_consistency_measures_the_acceleration_error_and_trains_only_accelerations(order):
    """Later velocities made by the closed form params_at: the gap is 0 for the true accelerations and,
    for accelerations off by d (velocities exact), exactly mean|d_a| + mean|d_eps| (in acceleration units)."""
    g = torch.Generator().manual_seed(3)
    true = DynamicsParams(*(torch.randn(16, 3, generator=g, dtype=f64) for _ in range(2 * order)))
    s = -0.07
    later = params_at(true, s)
    assert acceleration_consistency(true, later, s).item() < 1e-12
    d_a, d_e = torch.randn(16, 3, generator=g, dtype=f64), torch.randn(16, 3, generator=g, dtype=f64)
    learned = true._replace(
        acceleration=true.acceleration + d_a, angular_acceleration=true.angular_acceleration + d_e
    )
    learned = DynamicsParams(*(None if p is None else p.clone().requires_grad_() for p in learned))
    gap = acceleration_consistency(learned, later, s)
    torch.testing.assert_close(gap, d_a.abs().mean() + d_e.abs().mean())
    gap.backward()
    assert learned.velocity.grad is None and learned.angular_velocity.grad is None
    assert learned.acceleration.grad.abs().sum() > 0


@pytest.mark.parametrize("s", [0.13, -0.07])
def test_second_order_consistency_node_gives_autograds_bits(s):
    """The second-order gap as one autograd node against the composition of PyTorch ops it replaces:
    the same value and accelerations' gradients, bit for bit (float32, some gaps exactly zero)."""
    g = torch.Generator().manual_seed(4)
    params = DynamicsParams(*(torch.randn(300, 3, generator=g) for _ in range(4)))
    later = params_at(params, s)._replace(
        velocity=params_at(params, s).velocity + torch.randn(300, 3, generator=g)
    )
    later.velocity[:20] = params_at(params, s).velocity[:20]  # (|0|'s gradient: sign 0)
    ours = DynamicsParams(*(p.clone().requires_grad_() for p in params[:4]))
    gap = acceleration_consistency(ours, later, s)
    gap.backward()
    ref = DynamicsParams(*(p.clone().requires_grad_() for p in params[:4]))
    v, w = (
        ref.velocity.detach() + s * ref.acceleration,
        ref.angular_velocity.detach() + s * ref.angular_acceleration,
    )
    expected = ((v - later.velocity).abs().mean() + (w - later.angular_velocity).abs().mean()) / abs(s)
    expected.backward()
    assert torch.equal(gap, expected)
    assert torch.equal(ours.acceleration.grad, ref.acceleration.grad)
    assert torch.equal(ours.angular_acceleration.grad, ref.angular_acceleration.grad)
    assert ours.velocity.grad is None and ours.angular_velocity.grad is None


def test_a_spinning_projectile_needs_the_third_order_term():
    """With the jerk term RK4 reaches the closed form; without it (the second-order system) the
    trajectory is off by about |w x a| t^3 / 6 whatever the step (docs/PHYSICS.md)."""
    x0, q0 = start_state()
    (full, exact), (second_order, _) = spinning_projectile(3), spinning_projectile(2)
    errors = [
        (integrate(x0, q0, params, T, T / 256, "rk4")[0] - exact(x0, q0, T)[0]).norm(dim=-1)
        for params in (full, second_order)
    ]
    assert errors[0].max() < 1e-6
    bound = full.jerk.norm(dim=-1) * T**3 / 6  # |w x a| t^3 / 6
    assert (errors[1] > 0.2 * bound).all() and (errors[1] < 5 * bound).all()
