"""Parts on no joint (``extrapolation.joint_laws``): a part that neither turns on a hinge nor slides on
a rail nor bounces on a floor, whose centre moves in two or three coordinates at once (a disc held by
springs, a ball rolling in a bowl, a puck sliding on after an impact).

The part's rigid transforms from the handover to each frame (``joints.part_transforms``) carry its
centre (its Gaussians' mean at the handover) along a path ``c(t)`` [T, 3], the mean of its Gaussians
in each frame also where they slide over it (a spinning ball); its model is the identified model of
its coordinates along the directions it moves in (``motion_axes``), together, ``c'' = f(c, c')``
(``physics/identify.py``: coupled springs,
damping, friction, a constant force, split at the velocity jumps of an impact), and the part turns at
the mean angular velocity of its last frames' rigid turns. It is chosen as a joint's model is (the
held-out end of the span, ``joint_law_holdout``): adopted only where it is more than a constant
acceleration (which the learned physics is), is stable, beats moving on at the last velocity, fits the
whole path, and predicts the part's positions on the held-out frames better than ``joint_law_tolerance``
times the learned physics started at the same frame. No images.

M: a part's Gaussians, T: frames, H: held-out frames.
"""

from __future__ import annotations

import numpy as np
import torch

from ..physics.identify import holdout_split, identify
from ..physics.so3 import quat_to_axis_angle, rodrigues, rotmat_to_quat
from .joint_motion import rms_distance

MOTION_SPREAD = 0.02
"""Smallest spread of the centre's path along a direction, relative to its largest, for that direction
to be one of its model's coordinates; along the others it holds its place (the model of a coordinate
that does not move is its noise)."""
SPIN_FRAMES = 4
"""The last frames whose rigid turns give the part's angular velocity."""


def spin(rotation: torch.Tensor, times: np.ndarray, frames: int = SPIN_FRAMES) -> torch.Tensor:
    """[3] the mean angular velocity (world frame) of the rigid turns between the last ``frames`` + 1 of
    the part's transforms ``rotation`` [T, 3, 3] at ``times`` [T]."""
    rates = []
    for k in range(max(0, len(times) - frames - 1), len(times) - 1):
        turn = rotation[k + 1] @ rotation[k].T
        rates.append(quat_to_axis_angle(rotmat_to_quat(turn)) / float(times[k + 1] - times[k]))
    return torch.stack(rates).mean(0) if rates else torch.zeros(3, dtype=torch.float64)


def motion_axes(path: np.ndarray, spread: float = MOTION_SPREAD) -> tuple[np.ndarray, np.ndarray]:
    """``(origin [3], basis [k, 3])``: the mean of the centre's ``path`` [T, 3] and the principal
    directions along which it moves more than ``spread`` of its largest spread (a disc on a table:
    the table's two; a fall: one), the coordinates of its model."""
    origin = path.mean(0)
    _, sigma, axes = np.linalg.svd(path - origin, full_matrices=False)
    return origin, axes[sigma > spread * max(float(sigma[0]), 1e-300)]


def carried(start: torch.Tensor, centre: torch.Tensor, turn_rate: torch.Tensor, centres, s) -> torch.Tensor:
    """[K, M, 3] the points ``start`` [M, 3] about their ``centre`` [3] turned at ``turn_rate`` [3] for
    the times ``s`` [K] and moved to the ``centres`` [K, 3]."""
    out = []
    for c, dt in zip(torch.as_tensor(np.asarray(centres)), s, strict=True):
        out.append((start - centre) @ rodrigues(turn_rate * float(dt)).T + c)
    return torch.stack(out)


def choose_unjointed(
    rotation: torch.Tensor,
    translation: torch.Tensor,
    x0: torch.Tensor,
    truth: torch.Tensor,
    times: list[float],
    rows: torch.Tensor,
    learned,
    settings,
) -> tuple[dict | None, dict]:
    """``(stored part or None, report)`` of the Gaussians ``rows`` whose means are ``x0`` [M, 3] at the
    handover ``times[-1]`` and ``truth`` [T, M, 3] at the increasing ``times`` [T], carried there by the
    rigid transforms ``rotation`` [T, 3, 3], ``translation`` [T, 3] (module docstring); ``learned``
    the joint laws' ``_LearnedBacktest``. The stored part: ``{"joint": "free", "pivot"`` (its centre
    at the handover) ``, "spin"`` [3] ``, "model"`` (``IdentifiedModel.to_dict`` of the centre)``}``."""
    t = np.asarray(times, dtype=np.float64)
    centre = x0.double().cpu().mean(0)
    path = (rotation @ centre + translation).numpy()  # [T, 3] the centre over the frames
    origin, basis = motion_axes(path)
    n = holdout_split(len(t), settings.joint_law_holdout)
    model = identify(t, (path - origin) @ basis.T, holdout_fraction=settings.joint_law_holdout)
    entry: dict = {"gaussians": int(rows.sum()), "joint": "free", "adopted": False, **model.report()}
    if model.held_out_path is None or not np.isfinite(model.coefficients).all():
        return None, {**entry, "why": f"{model.why}: the learned physics"}
    turn_rate = spin(rotation[:n], t[:n])
    still = path[n - 1] - (path[n - 1] - origin) @ basis.T @ basis  # the centre off the axes, held
    centres = still + model.held_out_path @ basis
    law_means = carried(truth[n - 1], torch.from_numpy(path[n - 1]), turn_rate, centres, t[n:] - t[n - 1])
    learned_means = learned.means(float(t[n - 1]), [float(s) for s in t[n:]])[:, rows.cpu()]
    entry["position_rms"] = {
        "law": rms_distance(law_means, truth[n:]),
        "learned": rms_distance(learned_means, truth[n:]),
    }
    span = float(t[-1] - t[0])
    if model.active_kinds <= {"1"}:
        why = "a constant acceleration, which the learned physics is: the learned physics"
    elif not model.adopted:
        why = f"{model.why}: the learned physics"
    elif model.growth_rate() * span > 1.0:
        why = "unstable (a small departure grows e-fold within the span): the learned physics"
    elif not entry["position_rms"]["law"] < settings.joint_law_tolerance * entry["position_rms"]["learned"]:
        why = "the learned physics predicts the held-out frames as well: the learned physics"
    else:
        part = {
            "joint": "free",
            "pivot": torch.from_numpy(path[-1].copy()),
            "basis": torch.from_numpy(basis.copy()),
            "spin": spin(rotation, t),
            "model": model.to_dict(),
            "parent": None,
        }
        return part, {**entry, "adopted": True, "why": "adopted"}
    return None, {**entry, "why": why}
