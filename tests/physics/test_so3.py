"""Quaternions, rotation matrices, Rodrigues' formula: identities against independent references."""

import math

import pytest
import torch

from tracegs.physics.so3 import (
    axis_angle_to_quat,
    quat_canonical,
    quat_multiply,
    quat_normalize,
    quat_to_axis_angle,
    quat_to_rotmat,
    rodrigues,
    rotmat_to_quat,
    skew,
)

f64 = torch.float64


def random_quats(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return quat_normalize(torch.randn(n, 4, generator=g, dtype=f64))


def random_axes(n: int, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=f64)
    return v / v.norm(dim=-1, keepdim=True)


def near_half_turns() -> torch.Tensor:
    """Rotation vectors of angle pi and just below/above it, about random and coordinate axes."""
    axes = torch.cat([random_axes(20), torch.eye(3, dtype=f64), -torch.eye(3, dtype=f64)])
    angles = torch.tensor([math.pi, math.pi - 1e-7, math.pi - 1e-4, math.pi + 1e-6], dtype=f64)
    return (angles[:, None, None] * axes[None]).reshape(-1, 3)


def assert_same_rotation(q1: torch.Tensor, q2: torch.Tensor, atol: float = 1e-10) -> None:
    torch.testing.assert_close(quat_canonical(q1), quat_canonical(q2), atol=atol, rtol=0)


def test_skew_is_cross_product():
    g = torch.Generator().manual_seed(2)
    a, b = torch.randn(2, 50, 3, generator=g, dtype=f64)
    torch.testing.assert_close(skew(a) @ b[..., None], torch.linalg.cross(a, b)[..., None])
    torch.testing.assert_close(skew(a), -skew(a).transpose(-1, -2))


def test_quat_to_rotmat_is_a_rotation():
    R = quat_to_rotmat(random_quats(100))
    eye = torch.eye(3, dtype=f64).expand_as(R)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(100, dtype=f64))
    # normalises its input: a scaled quaternion gives the same matrix
    torch.testing.assert_close(quat_to_rotmat(3.7 * random_quats(100)), R)


def test_quat_product_is_matrix_product():
    q1, q2 = random_quats(100, seed=3), random_quats(100, seed=4)
    torch.testing.assert_close(quat_to_rotmat(quat_multiply(q1, q2)), quat_to_rotmat(q1) @ quat_to_rotmat(q2))
    # the product of unit quaternions is unit
    torch.testing.assert_close(quat_multiply(q1, q2).norm(dim=-1), torch.ones(100, dtype=f64))


@pytest.mark.parametrize("which", ["random", "half_turn", "identity"])
def test_rotmat_quat_round_trip(which):
    if which == "random":
        q = random_quats(200)
    elif which == "half_turn":
        q = axis_angle_to_quat(near_half_turns())
    else:
        q = torch.tensor([[1.0, 0, 0, 0], [-1.0, 0, 0, 0]], dtype=f64)
    R = quat_to_rotmat(q)
    q_back = rotmat_to_quat(R)
    assert (q_back[:, 0] >= 0).all()
    torch.testing.assert_close(q_back.norm(dim=-1), torch.ones(len(q), dtype=f64))
    torch.testing.assert_close(quat_to_rotmat(q_back), R, atol=1e-12, rtol=0)
    if which != "half_turn":  # at w = 0 both signs are canonical
        assert_same_rotation(q_back, q)


def test_rotmat_to_quat_float32_near_half_turn_is_accurate():
    # the trace formula alone loses all accuracy here; Shepperd's branch must be used
    rotvec = near_half_turns().float()
    R = rodrigues(rotvec)
    torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(R)), R, atol=2e-6, rtol=0)


def test_rotmat_to_quat_gradients_are_finite():
    for rotvec in (near_half_turns()[:8], torch.zeros(2, 3, dtype=f64), 0.7 * random_axes(4)):
        R = rodrigues(rotvec).requires_grad_(True)
        rotmat_to_quat(R).sum().backward()
        assert torch.isfinite(R.grad).all()
    R = rodrigues(0.9 * random_axes(3)).requires_grad_(True)
    assert torch.autograd.gradcheck(rotmat_to_quat, (R,))


@pytest.mark.parametrize("scale", [1.0, 1e-2, 1.1e-3, 0.9e-3, 1e-5, 1e-9, 0.0])
def test_rodrigues_matches_matrix_exponential(scale):
    g = torch.Generator().manual_seed(5)
    rotvec = scale * torch.randn(30, 3, generator=g, dtype=f64)
    rotvec = torch.cat([rotvec, scale * 3.0 * random_axes(3)])  # up to ~pi as well
    expected = torch.linalg.matrix_exp(skew(rotvec))
    torch.testing.assert_close(rodrigues(rotvec), expected, atol=1e-14, rtol=0)
    torch.testing.assert_close(quat_to_rotmat(axis_angle_to_quat(rotvec)), expected, atol=1e-14, rtol=0)


def test_rodrigues_and_quat_gradients_at_zero():
    # d R / d v_i at v = 0 is skew(e_i): finite and exact, not NaN
    rotvec = torch.zeros(3, dtype=f64, requires_grad=True)
    jac = torch.autograd.functional.jacobian(rodrigues, rotvec)  # [3, 3, 3(v)]
    torch.testing.assert_close(jac.permute(2, 0, 1), skew(torch.eye(3, dtype=f64)))
    # d q / d v at 0 is (0, I/2)
    jac_q = torch.autograd.functional.jacobian(axis_angle_to_quat, rotvec)  # [4, 3]
    expected = torch.cat([torch.zeros(1, 3, dtype=f64), 0.5 * torch.eye(3, dtype=f64)])
    torch.testing.assert_close(jac_q, expected)
    # the composition rotvec -> q -> rotvec is the identity with identity Jacobian at 0
    jac_rt = torch.autograd.functional.jacobian(lambda v: quat_to_axis_angle(axis_angle_to_quat(v)), rotvec)
    torch.testing.assert_close(jac_rt, torch.eye(3, dtype=f64))


@pytest.mark.parametrize("scale", [1.0, 1e-3, 1e-6])
def test_small_angle_paths_are_differentiable(scale):
    # gradcheck straddling the switch between the Taylor and the closed-form branches
    rotvec = (scale * random_axes(4)).requires_grad_(True)
    assert torch.autograd.gradcheck(rodrigues, (rotvec,))
    assert torch.autograd.gradcheck(axis_angle_to_quat, (rotvec,))
    assert torch.autograd.gradcheck(lambda v: quat_to_axis_angle(axis_angle_to_quat(v)), (rotvec,))


def test_axis_angle_round_trip():
    angles = torch.tensor([0.0, 1e-9, 1e-4, 0.5, 2.0, math.pi - 1e-3], dtype=f64)
    rotvec = (angles[:, None, None] * random_axes(10)[None]).reshape(-1, 3)
    q = axis_angle_to_quat(rotvec)
    torch.testing.assert_close(q.norm(dim=-1), torch.ones(len(q), dtype=f64))
    torch.testing.assert_close(quat_to_axis_angle(q), rotvec, atol=1e-12, rtol=0)
    # -q is the same rotation and gives the same rotation vector
    torch.testing.assert_close(quat_to_axis_angle(-q), rotvec, atol=1e-12, rtol=0)


def test_follows_input_dtype():
    for dtype in (torch.float32, torch.float64):
        v = torch.randn(4, 3, dtype=dtype)
        assert rodrigues(v).dtype == dtype
        assert axis_angle_to_quat(v).dtype == dtype
        assert rotmat_to_quat(rodrigues(v)).dtype == dtype
