"""Joints: a hinge's axis, pivot and angles and a slider's direction and positions are recovered
from rigid transforms, and turned back into the same transforms."""

import math

import torch

from tracegs.physics.joint import fit_hinge, fit_slider, hinge_transforms, slider_transforms
from tracegs.physics.so3 import quat_to_rotmat, rodrigues

DT = torch.float64


def hinge_motion(axis, pivot, angles, base_rotation, base_translation):
    turn = rodrigues(angles[:, None] * axis)
    return turn @ base_rotation, (base_translation - pivot) @ turn.transpose(1, 2) + pivot


def test_hinge_axis_pivot_and_angles_recovered_and_turned_back():
    torch.manual_seed(0)
    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=DT), dim=0)
    pivot = torch.tensor([0.2, 0.1, -0.4], dtype=DT)
    pivot = pivot - (pivot @ axis) * axis  # the point of the axis nearest the origin
    angles = 0.4 + 5.0 * torch.linspace(0, 1, 30, dtype=DT) ** 2  # past pi: unwrapped
    base_r = quat_to_rotmat(torch.tensor([0.9, 0.1, -0.3, 0.2], dtype=DT))
    base_t = torch.tensor([1.0, -0.5, 0.3], dtype=DT)
    R, T = hinge_motion(axis, pivot, angles, base_r, base_t)
    hinge, q = fit_hinge(R, T)
    torch.testing.assert_close(hinge.axis, axis, rtol=0, atol=1e-9)
    torch.testing.assert_close(hinge.pivot, pivot, rtol=0, atol=1e-9)
    torch.testing.assert_close(q, angles - angles[0], rtol=0, atol=1e-9)
    R2, T2 = hinge_transforms(hinge, q)
    torch.testing.assert_close(R2, R, rtol=0, atol=1e-9)
    torch.testing.assert_close(T2, T, rtol=0, atol=1e-9)


def test_hinge_from_noisy_transforms():
    torch.manual_seed(1)
    axis = torch.tensor([0.0, 0.0, 1.0], dtype=DT)
    pivot = torch.tensor([0.5, 0.0, 0.0], dtype=DT)
    angles = torch.sin(torch.linspace(0, 3, 40, dtype=DT))  # swings back and forth
    R, T = hinge_motion(axis, pivot, angles, torch.eye(3, dtype=DT), torch.zeros(3, dtype=DT))
    R = rodrigues(1e-3 * torch.randn(40, 3, dtype=DT)) @ R
    T = T + 1e-3 * torch.randn(40, 3, dtype=DT)
    hinge, q = fit_hinge(R, T, centre=torch.tensor([0.0, 0.0, 0.3], dtype=DT))
    assert float(hinge.axis @ axis) > math.cos(1e-2)
    torch.testing.assert_close(hinge.pivot, torch.tensor([0.5, 0.0, 0.3], dtype=DT), rtol=0, atol=1e-2)
    assert float((q - (angles - angles[0])).abs().max()) < 5e-3


def test_slider_direction_and_positions_recovered_and_shifted_back():
    direction = torch.nn.functional.normalize(torch.tensor([1.0, 2.0, -0.5], dtype=DT), dim=0)
    positions = 0.3 * torch.linspace(0, 1, 25, dtype=DT) - 0.1 * torch.linspace(0, 1, 25, dtype=DT) ** 2
    base_r = quat_to_rotmat(torch.tensor([0.7, 0.2, 0.1, -0.4], dtype=DT)).expand(25, 3, 3)
    T = torch.tensor([0.1, 0.2, 0.3], dtype=DT) + positions[:, None] * direction
    slider, q = fit_slider(base_r, T)
    torch.testing.assert_close(slider.direction, direction, rtol=0, atol=1e-9)
    torch.testing.assert_close(q, positions - positions[0], rtol=0, atol=1e-9)
    R2, T2 = slider_transforms(slider, q)
    torch.testing.assert_close(R2, base_r, rtol=0, atol=1e-9)
    torch.testing.assert_close(T2, T, rtol=0, atol=1e-9)


def test_a_bob_whose_shape_turns_less_than_its_arc_gets_its_angle_from_its_positions():
    """A compact bob 0.9 below its pivot swings by q(t); its own shape is turned back by 15% of q about
    its centre (what f_defo did on the pendulum scene): the rigid fits read 0.85 q, the positions q."""
    from tracegs.physics.free_body import fit_rigid_transform
    from tracegs.physics.joint import refine_hinge

    torch.manual_seed(2)
    axis, pivot = torch.tensor([0.0, 1.0, 0.0], dtype=DT), torch.tensor([0.0, 0.0, 0.52], dtype=DT)
    bob = torch.tensor([0.0, 0.0, -0.4], dtype=DT) + 0.06 * torch.randn(300, 3, dtype=DT)
    angles = 0.8 * torch.cos(5.0 * torch.linspace(0, 0.7, 42, dtype=DT)) - 0.6
    path = []
    for q in angles:
        turn, back = rodrigues(q * axis), rodrigues(-0.15 * q * axis)
        centre = turn @ (bob.mean(0) - pivot) + pivot
        path.append(((bob - bob.mean(0)) @ (back @ turn).T) + centre)
    path = torch.stack(path)
    x0 = path[-1]
    fits = [fit_rigid_transform(x0, p) for p in path]
    R, T = torch.stack([r for r, _ in fits]), torch.stack([t for _, t in fits])
    rigid, q_rigid = fit_hinge(R, T, centre=x0.mean(0))
    truth = angles - angles[0]
    assert float((q_rigid.abs().max() - truth.abs().max()).abs()) > 0.1  # the shape's 15% short
    hinge, q = refine_hinge(x0, path, rigid)
    sign = float(torch.sign(hinge.axis @ axis))
    assert float((sign * q - truth).abs().max()) < 0.01  # 0.24 from the rigid fits
    assert float((hinge.pivot - pivot)[[0, 2]].norm()) < 0.01  # (free along the axis)
    R2, T2 = hinge_transforms(hinge, q)
    carried = x0 @ R2.transpose(1, 2) + T2[:, None]
    assert float((carried - path).norm(dim=-1).mean()) < 0.02


def test_refine_hinge_keeps_an_exact_hinge():
    from tracegs.physics.joint import refine_hinge

    axis = torch.nn.functional.normalize(torch.tensor([0.3, -0.5, 0.8], dtype=DT), dim=0)
    pivot = torch.tensor([0.2, 0.1, -0.4], dtype=DT)
    pivot = pivot - (pivot @ axis) * axis
    angles = torch.sin(torch.linspace(0, 3, 30, dtype=DT))
    x0 = torch.randn(50, 3, dtype=DT, generator=torch.Generator().manual_seed(3))
    R, T = hinge_motion(axis, pivot, angles - angles[-1], torch.eye(3, dtype=DT), torch.zeros(3, dtype=DT))
    path = x0 @ R.transpose(1, 2) + T[:, None]
    hinge, q = refine_hinge(x0, path, fit_hinge(R, T)[0])
    torch.testing.assert_close(q, angles - angles[0], rtol=0, atol=1e-6)
    torch.testing.assert_close(hinge.axis, axis, rtol=0, atol=1e-6)
    R2, T2 = hinge_transforms(hinge, q)
    torch.testing.assert_close(x0 @ R2.transpose(1, 2) + T2[:, None], path, rtol=0, atol=1e-6)
