"""Joint parts after the handover: the rigid motion of each part that ``joints.py`` gave an identified
model (a hinge or a rail, a part turning on another's joint, a thrown part), from its coordinate
integrated by that model, and the Gaussians moved by it."""

from __future__ import annotations

import torch

from ..physics.identify import IdentifiedModel
from ..physics.joint import Hinge, Slider, hinge_transforms, slider_transforms
from ..physics.so3 import quat_multiply, quat_normalize, rodrigues, rotmat_to_quat


def joint_transforms(joint: dict, q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R [T, 3, 3], T [T, 3])`` of the stored ``joint`` (``fit_joint``) at the coordinates ``q`` [T]."""
    q = torch.as_tensor(q, dtype=torch.float64).reshape(-1)
    if joint["joint"] == "hinge":
        hinge = Hinge(joint["axis"], joint["pivot"], joint["base_rotation"], joint["base_translation"])
        return hinge_transforms(hinge, q)
    slider = Slider(joint["axis"], joint["base_rotation"], joint["base_translation"])
    return slider_transforms(slider, q)


def transformed_points(x0: torch.Tensor, rotation: torch.Tensor, translation: torch.Tensor) -> torch.Tensor:
    """[T, M, 3] the points ``x0`` [M, 3] carried by each transform (``R`` [T, 3, 3], ``T`` [T, 3])."""
    return x0.double().cpu() @ rotation.transpose(1, 2) + translation[:, None]


def rms_distance(a: torch.Tensor, b: torch.Tensor) -> float:
    """The RMS distance between the points ``a`` and ``b`` [..., 3]."""
    return float((a - b).square().sum(-1).mean().sqrt())


def coordinate_at(part: dict, t: float) -> float:
    """A stored part's coordinate ``q`` at ``t`` (>= the handover): its identified model
    (``IdentifiedModel.to_dict``) integrated from its state at the handover; a chain's link
    (``chain.py``) is its model's ``coordinate``."""
    model = IdentifiedModel.from_dict(part["model"])
    return float(model.rollout([max(t, model.t_end)])[0][0, part.get("coordinate", 0)])


def _start(part: dict) -> float:
    """A stored part's coordinate at the handover."""
    return float(part["model"]["q_end"][part.get("coordinate", 0)])


def _ends(part: dict, t: float) -> tuple[torch.Tensor, ...]:
    """``(R0, T0, R1, T1)``: a part's joint transforms at the handover and at ``t``."""
    q = torch.tensor([_start(part), coordinate_at(part, t)], dtype=torch.float64)
    rotation, translation = joint_transforms(part, q)
    return rotation[0], translation[0], rotation[1], translation[1]


def thrown_motion(part: dict, t0: float, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(turn [3, 3], shift [3])``: a stored thrown part's rigid motion from ``t0`` to ``t``
    (``thrown.py``): its spin about its centre at ``t0`` (``pivot``), which moves along the floor at
    ``velocity`` and bounces along ``axis``."""
    s = t - t0
    turn = rodrigues(part["spin"] * s)
    centre = part["pivot"] + part["velocity"] * s + part["axis"] * (coordinate_at(part, t) - _start(part))
    return turn, centre - turn @ part["pivot"]


def free_motion(part: dict, t0: float, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(turn [3, 3], shift [3])``: a stored part on no joint's rigid motion from ``t0`` to ``t``
    (``unjointed.py``): its centre at ``t0`` (``pivot``) moved along its axes (``basis``) as its
    model moves its coordinates from ``t0`` to ``t``, the part turned about it at ``spin``."""
    turn = rodrigues(part["spin"] * (t - t0))
    model = IdentifiedModel.from_dict(part["model"])
    moved = model.rollout([max(t, model.t_end)])[0][0] - model.q_end  # along its axes ("basis")
    centre = part["pivot"] + torch.from_numpy(moved) @ part["basis"]
    return turn, centre - turn @ part["pivot"]


def part_motion(parts: list[dict], k: int, t0: float, t: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(turn [3, 3], shift [3])``: the rigid motion of joint part ``k`` of ``parts`` from ``t0`` to
    ``t``, ``x -> turn x + shift``. A part with a ``parent`` (``on_frame``) turns on its joint in the
    parent's frame: ``A_p(t) C(t) A_p(t0)^-1``, ``A_p`` the parent's joint transform and ``C`` the
    part's own motion there."""
    if parts[k]["joint"] == "thrown":
        return thrown_motion(parts[k], t0, t)
    if parts[k]["joint"] == "free":
        return free_motion(parts[k], t0, t)
    r0, s0, r1, s1 = _ends(parts[k], t)
    turn = r1 @ r0.T
    shift = s1 - turn @ s0
    parent = parts[k].get("parent")
    if parent is None:
        return turn, shift
    p0, u0, p1, u1 = _ends(parts[parent], t)
    return p1 @ turn @ p0.T, p1 @ (shift - turn @ p0.T @ u0) + u1


def apply_joint_laws(
    gaussians: dict[str, torch.Tensor], start: dict[str, torch.Tensor], joints: dict, t: float
) -> dict[str, torch.Tensor]:
    """``gaussians`` with each joint part's Gaussians moved rigidly from their ``start`` (f_defo's state
    at the handover ``joints["t0"]``) to ``t``: its model integrated from its state there to ``q(t)``,
    and the joint's transform at ``q(t)`` relative to its transform at the handover."""
    means, quats = gaussians["means"].clone(), quat_normalize(gaussians["quats"]).clone()
    labels = joints["labels"].to(means.device)
    for k in range(len(joints["parts"])):
        rows = labels == k + 1
        if not bool(rows.any()):  # a turning part's frame only (``on_frame``)
            continue
        turn, shift = part_motion(joints["parts"], k, joints["t0"], t)
        x = start["means"][rows]
        means[rows] = (x.double() @ turn.to(x.device).T + shift.to(x.device)).to(x.dtype)
        q_turn = rotmat_to_quat(turn).to(dtype=quats.dtype, device=x.device)[None].expand(int(rows.sum()), 4)
        quats[rows] = quat_multiply(q_turn, quat_normalize(start["quats"][rows]))
    return {**gaussians, "means": means, "quats": quats}
