"""Ground-truth physics comparisons on synthetic scenes (``tracegs synth`` writes ``gt/``).

- 3D trajectory error: every Gaussian within ``radius`` of the ground-truth surface at t_max is given
  the rigid motion of the part it lies on; its predicted position at each future time is compared with
  where that motion takes it.
- Angular velocity: the w each part's Gaussians turn at from t_max (median vector; f_trd's, or the
  free body's where one moves them) against the closed form's angular velocity at that time: the angle between
  axes and the relative magnitude error; and
  (``omega_over_span``) the same at several query times of the training span, which shows where in
  time f_trd is accurate (the extrapolation starts from its value at the handover time).
N: Gaussians, M: ground-truth points, P: parts, T: times.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..extrapolate import Predictor
from ..physics.free_body import FreeBody


def _gt(data: Path):
    """``(points, part_ids, transforms, motions)`` of ``data/gt``: ``transforms(t)`` [P, 4, 4] rest ->
    world, ``motions`` by part id (``motion.json`` read once)."""
    from ..data.synth.motion import transforms_at

    gt = Path(data) / "gt"
    pts = np.load(gt / "points.npz")
    motions = _motions(data)
    return pts["points"], pts["part_ids"], lambda t: transforms_at(motions, t), motions


def ground_truth_problem(data: Path) -> str | None:
    """Why ``data/gt`` cannot be compared with (missing files, or another generator's layout), in words,
    or None when it holds what ``tracegs synth`` writes: ``motion.json`` (parts with ids 1..P, axis,
    angular velocity and acceleration) and ``points.npz`` (``points`` [M, 3], ``part_ids`` [M] in 1..P)."""
    import zipfile

    gt = Path(data) / "gt"
    motion, points = gt / "motion.json", gt / "points.npz"
    for path in (motion, points):
        if not path.is_file():
            return f"{path} not found"
    try:
        motions = _motions(data)
        count = len(motions)
        for m in motions:
            m.angular_velocity_at(0.0)
    except (ValueError, KeyError, TypeError, IndexError) as err:
        return f"{motion}: not the layout of tracegs synth ({type(err).__name__}: {err})"
    try:
        with np.load(points) as z:
            xyz, ids = np.asarray(z["points"], dtype=np.float64), np.asarray(z["part_ids"])
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as err:
        return f"{points}: not the layout of tracegs synth ({type(err).__name__}: {err})"
    if xyz.ndim != 2 or xyz.shape[1] != 3 or ids.shape != (len(xyz),) or len(xyz) == 0:
        return (
            f"{points}: expected points [M, 3] and part_ids [M], got {list(xyz.shape)} and {list(ids.shape)}"
        )
    if not np.issubdtype(ids.dtype, np.integer) or ids.min() < 1 or ids.max() > count:
        return f"{points}: part_ids must be the part ids of motion.json (1..{count})"
    return None


def _transform(T: np.ndarray, x: torch.Tensor) -> torch.Tensor:
    T = torch.as_tensor(T, dtype=x.dtype, device=x.device)
    return x @ T[:3, :3].T + T[:3, 3]


def _distance(x: torch.Tensor, surface: torch.Tensor) -> torch.Tensor:
    """[N] the distance from each point of ``x`` [N, 3] to the nearest of ``surface`` [M, 3]."""
    return torch.cat([torch.cdist(c, surface).min(dim=1).values for c in x.split(8192)])


OWNER_TIMES = 5
"""Times over [0, t] at which ``_parts_at`` compares each Gaussian's path with the parts'."""


def _parts_at(predictor: Predictor, t: float, gt, radius: float) -> tuple[torch.Tensor, torch.Tensor]:
    """``(means [N, 3], part id [N])`` of the Gaussians at time ``t`` (0: on no part). Of the parts whose
    surface lies within ``radius`` of a Gaussian at ``t``, it belongs to the one whose motion carries it
    along its own path best (the mean distance over ``OWNER_TIMES`` times from 0 to ``t``): where two
    parts touch (a disc on its pedestal), the nearest surface point can be either part's."""
    points, part_ids, transforms, _ = gt
    parts = sorted(int(p) for p in np.unique(part_ids))
    means = predictor.gaussians_at(t)["means"]
    T_t = transforms(t)  # [P, 4, 4], rest -> world at t
    near = []  # [P] x [N]: within radius of the part's surface at t
    for p in parts:
        surface = torch.as_tensor(points[part_ids == p], dtype=means.dtype, device=means.device)
        near.append(_distance(means, _transform(T_t[p - 1], surface)) <= radius)
    near = torch.stack(near)
    cost = torch.zeros(near.shape, dtype=means.dtype, device=means.device)
    for s in np.linspace(0.0, t, OWNER_TIMES)[:-1]:
        x_s, T_s = predictor.gaussians_at(float(s))["means"], transforms(float(s))
        for i, p in enumerate(parts):  # the part's motion from t back to s, applied to where it is at t
            cost[i] += (_transform(T_s[p - 1] @ np.linalg.inv(T_t[p - 1]), means) - x_s).norm(dim=-1)
    owner = torch.as_tensor(parts, device=means.device)[cost.masked_fill(~near, math.inf).argmin(dim=0)]
    return means, torch.where(near.any(dim=0), owner, torch.zeros_like(owner))


@torch.no_grad()
def physics_errors(
    predictor: Predictor, data: Path, times: list[float], radius: float = 0.03, positions=None
) -> dict:
    """Per-part trajectory error over ``times`` (> t_max) and angular-velocity error at t_max, for a
    trained run (``extrapolate.Predictor``); ``positions(t)`` [N, 3]: where another motion puts the
    Gaussians at ``t`` (a simulator's, ``export/simulate.py``), scored instead of the run's."""
    t_max = predictor.t_max
    gt = _gt(data)
    part_ids, transforms = gt[1], gt[2]
    parts = sorted(int(p) for p in np.unique(part_ids))
    T_start = transforms(t_max)
    x_start, owner = _parts_at(predictor, t_max, gt, radius)
    result = {"radius": radius, "parts": {}}
    per_time = {p: [] for p in parts}
    for t in times:
        x_pred = predictor.gaussians_at(t)["means"] if positions is None else positions(t)
        T_t = transforms(t)
        for p in parts:
            sel = owner == p
            if not bool(sel.any()):
                continue
            # motion of part p from t_max to t, applied to where the Gaussian was at t_max
            rel = T_t[p - 1] @ np.linalg.inv(T_start[p - 1])
            err = (x_pred[sel] - _transform(rel, x_start[sel])).norm(dim=-1).mean()
            per_time[p].append({"t": t, "error": float(err)})
    omega = _spin_at(predictor, x_start, t_max)
    motions = gt[3]
    for p in parts:
        sel = owner == p
        entry = {"gaussians": int(sel.sum()), "trajectory": per_time[p]}
        if per_time[p]:
            entry["mean_trajectory_error"] = float(np.mean([r["error"] for r in per_time[p]]))
        if omega is not None and bool(sel.any()):
            entry.update(_compare_omega(omega[sel].median(dim=0).values.cpu().numpy(), motions[p - 1], t_max))
        result["parts"][str(p)] = entry
    if omega is not None:
        result["omega_over_span"] = _omega_over_span(predictor, gt, motions, radius)
    return result


def _omega_over_span(predictor: Predictor, gt, motions: list, radius: float) -> list[dict]:
    """Relative error of each rotating part's median learned |w| at query times across the training
    span: fractions of t_max and the handover time."""
    t_max = predictor.t_max
    times = sorted({t_max * f for f in (0.25, 0.5, 0.75, 1.0)} | {predictor.handover_time()})
    rows = []
    for t in times:
        means, owner = _parts_at(predictor, t, gt, radius)
        omega = _learned_angular_velocity(predictor.model, means, t)
        row = {"t": t, "parts": {}}
        for p, motion in enumerate(motions, start=1):
            sel = owner == p
            cmp = (
                _compare_omega(omega[sel].median(dim=0).values.cpu().numpy(), motion, t) if sel.any() else {}
            )
            if "omega_rel_error" in cmp:
                row["parts"][str(p)] = {
                    "omega_learned_norm": float(np.linalg.norm(cmp["omega_learned"])),
                    "omega_gt_norm": float(np.linalg.norm(cmp["omega_gt"])),
                    "omega_rel_error": cmp["omega_rel_error"],
                }
        rows.append(row)
    return rows


def _spin_at(predictor: Predictor, means: torch.Tensor, t: float) -> torch.Tensor | None:
    """[N, 3] the angular velocity the future turns each Gaussian at, from ``t`` (after the handover):
    f_trd's, or its free body's where one moves it (``extrapolation.free_bodies``)."""
    omega = _learned_angular_velocity(predictor.model, means, t)
    bodies = predictor.state.free_bodies
    if (
        omega is None
        or bodies is None
        or not predictor.settings.free_bodies
        or len(omega) != len(bodies["labels"])
    ):
        return omega
    omega = omega.clone()
    labels = bodies["labels"].to(omega.device)
    for k, row in enumerate(bodies["bodies"]):
        omega[labels == k + 1] = FreeBody.from_tensor(row).w.to(omega)
    return omega


def _learned_angular_velocity(model, means: torch.Tensor, t: float) -> torch.Tensor | None:
    if getattr(model, "dynamics", None) is None:
        return None
    return model.query_dynamics(means, t).angular_velocity


def _motions(data: Path) -> list:
    """The parts' motions of ``data/gt/motion.json``, by part id (index p - 1 for part p)."""
    from ..data.synth.motion import load_motions  # (data.synth loads the renderer's modules)

    return load_motions(Path(data) / "gt" / "motion.json")


def _compare_omega(learned: np.ndarray, motion, t: float) -> dict:
    gt = np.asarray(motion.angular_velocity_at(t), dtype=np.float64).reshape(3)
    gt_mag, mag = float(np.linalg.norm(gt)), float(np.linalg.norm(learned))
    out = {"omega_learned": learned.tolist(), "omega_gt": gt.tolist(), "omega_abs_error": abs(mag - gt_mag)}
    if gt_mag > 1e-6:
        out["omega_rel_error"] = abs(mag - gt_mag) / gt_mag
        cos = float(np.dot(learned, gt) / max(mag * gt_mag, 1e-12))
        out["axis_error_deg"] = math.degrees(math.acos(max(-1.0, min(1.0, cos))))
    return out
