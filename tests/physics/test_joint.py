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
