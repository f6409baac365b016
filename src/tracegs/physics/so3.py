"""Rotations: quaternions, rotation matrices, rotation vectors and Rodrigues' formula.

...: any batch shape. Quaternions are scalar-first, ``[..., 4] = (w, x, y, z)``, as in 3DGS.
Rotation vectors (axis-angle) are ``[..., 3] = angle * unit_axis``; matrices are ``[..., 3, 3]``.

Every function here is differentiable everywhere it is called in training, including at the zero
rotation (where the textbook formulas divide by the angle): the small-angle paths use Taylor series
selected with ``torch.where`` on a "safe" angle, so that neither branch produces inf/NaN gradients.
Nothing here creates tensors on a fixed device: outputs follow the inputs' device and dtype.
"""

from __future__ import annotations

import torch

# Below this angle (radians) the Taylor branches are used. Their truncation error is O(theta^6),
# i.e. < 1e-19 here, and the closed-form branches are written in cancellation-free forms
# (1 - cos t = 2 sin^2(t/2)), so the switch point is not a trade-off between the two.
SMALL_ANGLE = 1e-3


def quat_multiply(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``q1 o q2`` [..., 4] (rotate by q2 first, then by q1).

    ``quat_to_rotmat(q1 o q2) == quat_to_rotmat(q1) @ quat_to_rotmat(q2)``; this is the "o" of the
    paper's deformation (Appendix, q_t = dq o q0).
    """
    w1, x1, y1, z1 = q1.unbind(-1)
    w2, x2, y2, z2 = q2.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def quat_conjugate(q: torch.Tensor) -> torch.Tensor:
    """The conjugate (the inverse for a unit quaternion) [..., 4]."""
    return q * q.new_tensor([1.0, -1.0, -1.0, -1.0])


def quat_normalize(q: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """``q / |q|`` [..., 4], with the norm clamped at ``eps`` so a zero quaternion gives no NaN."""
    return q / q.norm(dim=-1, keepdim=True).clamp_min(eps)


def quat_canonical(q: torch.Tensor) -> torch.Tensor:
    """``q`` or ``-q`` (the same rotation), whichever has ``w >= 0`` [..., 4]."""
    return torch.where(q[..., :1] < 0, -q, q)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Rotation matrix [..., 3, 3] of a quaternion [..., 4] (normalised first)."""
    w, x, y, z = quat_normalize(q).unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def _sqrt_positive(x: torch.Tensor) -> torch.Tensor:
    """``sqrt(max(x, 0))`` with a zero (not infinite) gradient where ``x <= 0``."""
    positive = x > 0
    return torch.where(
        positive, torch.sqrt(torch.where(positive, x, torch.ones_like(x))), torch.zeros_like(x)
    )


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """Unit quaternion [..., 4] with ``w >= 0`` of a rotation matrix [..., 3, 3] (Shepperd's method).

    Four candidate quaternions are formed, each dividing by one of ``2|w|, 2|x|, 2|y|, 2|z|``; the one
    whose divisor is largest (>= 1 for a rotation) is kept, so the result is accurate and has finite
    gradients for every rotation, including the 180-degree ones where the trace formula fails.
    """
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = R.flatten(-2).unbind(-1)
    # 4 q_i^2 for i = w, x, y, z
    four_q2 = torch.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22], dim=-1
    )
    two_q_abs = _sqrt_positive(four_q2)  # [..., 4] = 2 |q_i|
    # row i: 4 q_i * (w, x, y, z), i.e. the quaternion scaled by 4 q_i (sign of q_i taken positive)
    candidates = torch.stack(
        [
            torch.stack([four_q2[..., 0], m21 - m12, m02 - m20, m10 - m01], dim=-1),
            torch.stack([m21 - m12, four_q2[..., 1], m10 + m01, m02 + m20], dim=-1),
            torch.stack([m02 - m20, m10 + m01, four_q2[..., 2], m12 + m21], dim=-1),
            torch.stack([m10 - m01, m20 + m02, m21 + m12, four_q2[..., 3]], dim=-1),
        ],
        dim=-2,
    )  # [..., 4, 4]
    # the clamp only affects the rows that are not selected (the selected divisor is >= 1)
    candidates = candidates / (2 * two_q_abs.clamp_min(0.1))[..., None]
    best = two_q_abs.argmax(dim=-1, keepdim=True)  # [..., 1]
    index = best[..., None].expand(*best.shape[:-1], 1, 4)
    q = torch.take_along_dim(candidates, index, dim=-2).squeeze(-2)
    return quat_canonical(quat_normalize(q))


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``K`` [..., 3, 3] of ``v`` [..., 3], so that ``K @ b == cross(v, b)``.

    Appendix (Cross-Product Matrix) of the paper. Note: the paper's matrix has a sign typo, with
    ``K[1, 2] = +k1`` and ``K[2, 1] = +k1``; the correct entries (used here, and consistent with the
    paper's own expanded product above that matrix) are ``K[1, 2] = -k1`` and ``K[2, 1] = +k1``.
    """
    k1, k2, k3 = v.unbind(-1)
    zero = torch.zeros_like(k1)
    rows = [
        zero, -k3, k2,
        k3, zero, -k1,
        -k2, k1, zero,
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).unflatten(-1, (3, 3))


def _angle_squared_and_safe_angle(
    rotvec: torch.Tensor, eps: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``theta^2`` [...], a mask of small angles [...], and ``theta`` with small angles replaced by 1."""
    theta2 = (rotvec * rotvec).sum(-1)
    small = theta2 < eps * eps
    safe_theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    return theta2, small, safe_theta


def rodrigues(rotvec: torch.Tensor, eps: float = SMALL_ANGLE) -> torch.Tensor:
    """Rotation matrix [..., 3, 3] of a rotation vector [..., 3] (Rodrigues' formula, Alg. 1).

    ``R = I + sin(t) K + (1 - cos t) K^2`` with ``K`` the cross-product matrix of the unit axis, written
    with the unnormalised ``skew(rotvec)`` as ``I + (sin t / t) S + ((1 - cos t) / t^2) S^2``. Both
    coefficients are even functions of t; below ``eps`` they are replaced by their Taylor series in
    ``t^2`` (no division, no sqrt), so ``rodrigues(0) = I`` with the exact gradient ``skew(e_i)``.
    """
    theta2, small, t = _angle_squared_and_safe_angle(rotvec, eps)
    half_sinc = torch.sin(t / 2) / (t / 2)
    a = torch.where(small, 1 - theta2 / 6 + theta2 * theta2 / 120, torch.sin(t) / t)
    b = torch.where(small, 0.5 - theta2 / 24 + theta2 * theta2 / 720, 0.5 * half_sinc * half_sinc)
    S = skew(rotvec)
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + a[..., None, None] * S + b[..., None, None] * (S @ S)


def axis_angle_to_quat(rotvec: torch.Tensor, eps: float = SMALL_ANGLE) -> torch.Tensor:
    """Unit quaternion [..., 4] of a rotation vector [..., 3]: ``(cos(t/2), sin(t/2) axis)``.

    Safe at 0 (Taylor series of ``cos(t/2)`` and ``sin(t/2)/t`` below ``eps``).
    """
    theta2, small, t = _angle_squared_and_safe_angle(rotvec, eps)
    w = torch.where(small, 1 - theta2 / 8 + theta2 * theta2 / 384, torch.cos(t / 2))
    s = torch.where(small, 0.5 - theta2 / 48 + theta2 * theta2 / 3840, torch.sin(t / 2) / t)
    return torch.cat([w[..., None], s[..., None] * rotvec], dim=-1)


def quat_to_axis_angle(q: torch.Tensor, eps: float = SMALL_ANGLE) -> torch.Tensor:
    """Rotation vector [..., 3] with angle in [0, pi] of a quaternion [..., 4] (normalised first)."""
    q = quat_canonical(quat_normalize(q))
    w, xyz = q[..., 0], q[..., 1:]
    s2 = (xyz * xyz).sum(-1)  # sin^2(t/2)
    small = s2 < (eps / 2) ** 2
    s = torch.sqrt(torch.where(small, torch.ones_like(s2), s2))
    # t / sin(t/2) with t = 2 atan2(s, w); for small s: (2 / w) (1 - s^2 / (3 w^2)), w ~ 1 there
    factor = torch.where(small, 2 / w * (1 - s2 / (3 * w * w)), 2 * torch.atan2(s, w) / s)
    return factor[..., None] * xyz
