"""One-degree-of-freedom joints: a rigid part's per-frame transforms as one coordinate ``q``, and back.

A part's transforms ``x_k = R_k x + T_k`` (its points ``x`` in a reference state, e.g. f_defo's at some
time, carried to frame k: ``free_body.fit_rigid_transform``) are, for a part on a hinge, turns by an
angle ``q_k`` about a fixed axis through a fixed pivot, and for a part on a rail, shifts by ``q_k``
along a fixed direction. ``fit_hinge`` and ``fit_slider`` find the axis or direction and ``q`` [T];
``hinge_transforms`` and ``slider_transforms`` turn any ``q`` (a force law's prediction,
``physics/force_law.py``) back into transforms. Rotations as in ``so3.py`` (wxyz quaternions,
rotation vectors, matrices); torch float64.

T: frames.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .so3 import axis_angle_to_quat, quat_to_rotmat, rotmat_to_quat


@dataclass(frozen=True)
class Hinge:
    """Turns by ``q`` about the unit ``axis`` [3] through ``pivot`` [3] (right-hand rule), applied after
    the transform at ``q = 0``: ``base_rotation`` [3, 3], ``base_translation`` [3]."""

    axis: torch.Tensor
    pivot: torch.Tensor
    base_rotation: torch.Tensor
    base_translation: torch.Tensor


@dataclass(frozen=True)
class Slider:
    """Shifts by ``q`` along the unit ``direction`` [3] of the transform at ``q = 0``: ``base_rotation``
    [3, 3], ``base_translation`` [3]."""

    direction: torch.Tensor
    base_rotation: torch.Tensor
    base_translation: torch.Tensor


def _principal_direction(rows: torch.Tensor) -> torch.Tensor:
    """[3] unit direction that the rows [T, 3] lie along (through the origin), sign-free."""
    return torch.linalg.svd(rows, full_matrices=False).Vh[0]


def _unwrap(angles: torch.Tensor) -> torch.Tensor:
    """[T] ``angles`` with the jumps of more than pi between frames removed (by multiples of 2 pi)."""
    jumps = torch.diff(angles, prepend=angles[:1])
    turns = torch.round(jumps / (2 * torch.pi))
    return angles - 2 * torch.pi * torch.cumsum(turns, 0)


def fit_hinge(
    rotations: torch.Tensor, translations: torch.Tensor, centre: torch.Tensor | None = None
) -> tuple[Hinge, torch.Tensor]:
    """``(hinge, q [T])`` of the transforms ``rotations`` [T, 3, 3], ``translations`` [T, 3], with
    ``q = 0`` at frame 0 and ``q`` continuous (unwrapped) over the frames.

    The relative turns ``D_k = R_k R_0^T`` share the axis: the principal direction of their quaternions'
    vector parts, signed so that the last frame's angle is >= 0. ``q_k = 2 atan2(n . xyz_k, w_k)``. The
    pivot ``p`` solves ``(I - D_k) p = T_k - D_k T_0`` for all k in least squares; the axis leaves it
    free along itself, where it is taken nearest ``centre`` (default: the origin)."""
    R, T = rotations.double(), translations.double()
    relative = R @ R[0].T  # [T, 3, 3]
    quats = rotmat_to_quat(relative)  # [T, 4], w >= 0
    axis = _principal_direction(quats[:, 1:])
    angles = _unwrap(2 * torch.atan2(quats[:, 1:] @ axis, quats[:, 0]))
    if angles[-1] < 0:
        axis, angles = -axis, -angles
    centre = torch.zeros(3, dtype=R.dtype) if centre is None else centre.double()
    eye = torch.eye(3, dtype=R.dtype)
    system = (eye - relative).reshape(-1, 3)  # [3T, 3]
    target = (T - relative @ T[0] - (eye - relative) @ centre).reshape(-1, 1)
    plane = torch.linalg.svd(eye - torch.outer(axis, axis)).U[:, :2]  # [3, 2] across the axis
    offset = plane @ torch.linalg.lstsq(system @ plane, target).solution[:, 0]
    return Hinge(axis, centre + offset, R[0], T[0]), angles


def turn_angles(
    points: torch.Tensor, path: torch.Tensor, axis: torch.Tensor, pivot: torch.Tensor
) -> torch.Tensor:
    """[T] the angle about ``axis`` through ``pivot`` that best carries ``points`` [M, 3] to each frame's
    ``path`` [T, M, 3] in least squares: ``atan2(sum (a x b) . n, sum a . b)`` over the points' offsets
    ``a``, ``b`` across the axis (exact: a turn about a fixed axis leaves the offsets along it)."""
    n = axis / axis.norm()
    a = points - pivot
    a = a - (a @ n)[:, None] * n
    b = path - pivot
    b = b - (b @ n)[..., None] * n
    return torch.atan2((torch.cross(a.expand_as(b), b, dim=-1) @ n).sum(-1), (a * b).sum((-1, -2)))


def refine_hinge(points: torch.Tensor, path: torch.Tensor, hinge: Hinge) -> tuple[Hinge, torch.Tensor]:
    """``(hinge, q [T])`` refitted to the positions: the axis and pivot (started at ``hinge``'s) whose
    turns (``turn_angles``, one per frame) carry ``points`` [M, 3] (the part at a reference state) to
    ``path`` [T, M, 3] with the least RMS distance (``scipy.optimize.least_squares`` over two angles of
    the axis and two coordinates of the pivot across it); ``q = 0`` at frame 0, as ``fit_hinge``'s.
    The centroid's miss is weighted by the number of points, so it weighs more than all of them
    together: its path fixes a pivot far from the part, and a shape that turns less than the part
    (below) moves the centroid not at all (on such a bob, a 15% lag of its shape: an angle 0.4% off
    with this weight, 4% with the centroid as one more point).

    The turns of the per-frame rigid fits (``fit_hinge``'s input) read a part's angle from its shape,
    which f_defo keeps least well: a compact bob far from its pivot turned 15% less in them than along
    its arc. Its positions, at their lever arm, fix the angle."""
    from scipy.optimize import least_squares

    x, truth = points.double(), path.double()
    a0, p0 = hinge.axis.double() / hinge.axis.norm(), hinge.pivot.double()
    across = torch.linalg.svd(torch.eye(3, dtype=x.dtype) - torch.outer(a0, a0)).U[:, :2]  # [3, 2]

    def unpack(v):
        v = torch.as_tensor(v, dtype=x.dtype)
        axis = a0 + across @ v[:2]
        return axis / axis.norm(), p0 + across @ v[2:]

    def carried(axis, pivot):
        q = turn_angles(x, truth, axis, pivot)
        turn = quat_to_rotmat(axis_angle_to_quat(q[:, None] * axis))
        return (x - pivot) @ turn.transpose(1, 2) + pivot, q

    def residual(v):  # every point's, and the centroid's before them (module docstring)
        miss = carried(*unpack(v))[0] - truth
        return torch.cat([miss.reshape(-1), len(x) * miss.mean(1).reshape(-1)]).numpy()

    fit = least_squares(residual, [0.0, 0.0, 0.0, 0.0], x_scale="jac")
    axis, pivot = unpack(fit.x)
    q = _unwrap(carried(axis, pivot)[1])
    if q[-1] - q[0] < 0:
        axis, q = -axis, -q
    base = quat_to_rotmat(axis_angle_to_quat(q[0] * axis))
    return Hinge(axis, pivot, base, pivot - base @ pivot), q - q[0]


def hinge_transforms(hinge: Hinge, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R [T, 3, 3], T [T, 3])`` of the hinge turned by the angles ``q`` [T]."""
    turn = quat_to_rotmat(axis_angle_to_quat(q.double()[:, None] * hinge.axis))  # [T, 3, 3]
    rotation = turn @ hinge.base_rotation
    translation = ((hinge.base_translation - hinge.pivot) @ turn.transpose(1, 2)) + hinge.pivot
    return rotation, translation


def _mean_rotation(rotations: torch.Tensor) -> torch.Tensor:
    """[3, 3] the rotation nearest the mean of ``rotations`` [T, 3, 3] (chordal mean)."""
    u, _, vh = torch.linalg.svd(rotations.mean(0))
    d = torch.sign(torch.linalg.det(u @ vh))
    return u @ torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d])) @ vh


def fit_slider(rotations: torch.Tensor, translations: torch.Tensor) -> tuple[Slider, torch.Tensor]:
    """``(slider, q [T])`` of the transforms ``rotations`` [T, 3, 3], ``translations`` [T, 3]: the
    rotation their chordal mean, the direction the line that the translations lie along in least
    squares (signed so that the last frame's ``q`` is >= 0), ``q = 0`` at frame 0's point on it."""
    R, T = rotations.double(), translations.double()
    mean = T.mean(0)
    direction = _principal_direction(T - mean)
    q = (T - mean) @ direction
    if q[-1] - q[0] < 0:
        direction, q = -direction, -q
    base = mean + q[0] * direction
    return Slider(direction, _mean_rotation(R), base), q - q[0]


def slider_transforms(slider: Slider, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R [T, 3, 3], T [T, 3])`` of the slider shifted by ``q`` [T]."""
    q = q.double()
    rotation = slider.base_rotation.expand(len(q), 3, 3)
    return rotation, slider.base_translation + q[:, None] * slider.direction
