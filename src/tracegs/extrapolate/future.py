"""The one function that turns (model, post-training state, t) into Gaussians, for any time t.

Up to the handover (``extrapolation.handover_frames`` before t_max) f_defo places the Gaussians, as in
training; later the learned physics (f_trd, integrated from the handover) moves every Gaussian but
those that hold still (``still.py``: one code per Gaussian says which and why) and those that move as
free bodies (``free_bodies.py``) or on joints with force laws (``joints.py``). The methods without f_trd (DefGS, static 3DGS) render f_defo or the
canonical Gaussians at every time.
N: Gaussians.
"""

from __future__ import annotations

import torch

from ..physics.free_body import apply_free_bodies
from ..physics.integrate import num_substeps, step
from ..physics.so3 import quat_normalize
from .joint_motion import apply_joint_laws
from .state import ExtrapolationState
from .still import moving_after_handover
from .surface import SurfacePainters


def handover_time(model, t_max: float) -> float:
    """Last time rendered by f_defo alone; later times are integrated from it. f_defo is least
    constrained at the end of the training span, so (as the authors' code does) the physics takes over
    a few frames before the data ends."""
    return max(0.0, t_max - model.cfg.extrapolation.handover_frames * model.dt_max)


@torch.no_grad()
def gaussians_at(model, state: ExtrapolationState, t: float) -> dict[str, torch.Tensor]:
    """Geometry of the Gaussians at time ``t`` (``means`` [N, 3], ``quats`` [N, 4], log-``scales``
    [N, 3]): f_defo up to the handover, then the learned physics, the still Gaussians, the free
    bodies and the joint parts."""
    g = model.gaussians
    if model.cfg.method == "static":
        return {"means": g["means"], "quats": g["quats"], "scales": g["scales"]}
    if model.dynamics is None:
        return model.deform(t)
    if model.deformation is None:
        return physics_from(model, state, 0.0, t)
    t0 = handover_time(model, state.t_max)
    if t <= t0:
        return model.deform(t)
    start = model.deform(t0)  # where the physics, the free bodies and the joint parts start from
    gaussians = with_free_bodies(model, state, t0, t, physics_from(model, state, t0, t, start=start), start)
    return with_joint_laws(model, state, t0, t, gaussians, start)


def _chosen_here(entry: dict | None, t0: float, n: int) -> bool:
    """Whether a stored choice (free bodies, joint parts) was made for this handover and these ``n``
    Gaussians (not for another handover or another set of Gaussians)."""
    return abs(entry["t0"] - t0) <= 1e-9 and entry["labels"].shape[0] == n


def with_free_bodies(
    model, state: ExtrapolationState, t0: float, t: float, gaussians: dict, start: dict
) -> dict:
    """``gaussians`` (the learned physics at ``t``) with the free bodies' Gaussians moved as free bodies
    from ``start``, f_defo's state at ``t0`` (``physics/free_body.py``)."""
    bodies = state.free_bodies
    if not model.cfg.extrapolation.free_bodies or bodies is None or not len(bodies["bodies"]):
        return gaussians
    if not _chosen_here(bodies, t0, gaussians["means"].shape[0]):
        return gaussians
    labels = bodies["labels"].to(gaussians["means"].device)
    return apply_free_bodies(gaussians, start, labels, bodies["bodies"], t - t0)


def with_joint_laws(
    model, state: ExtrapolationState, t0: float, t: float, gaussians: dict, start: dict
) -> dict:
    """``gaussians`` with the joint parts' Gaussians moved by their force laws from ``start``, f_defo's
    state at ``t0`` (``joints.py``; ``extrapolation.joint_laws``)."""
    joints = state.joint_laws
    if not model.cfg.extrapolation.joint_laws or joints is None or not joints["parts"]:
        return gaussians
    if not _chosen_here(joints, t0, gaussians["means"].shape[0]):
        return gaussians
    return apply_joint_laws(gaussians, start, joints, t)


def physics_from(
    model,
    state: ExtrapolationState,
    t0: float,
    t: float,
    moving: torch.Tensor | None = None,
    start: dict[str, torch.Tensor] | None = None,
) -> dict[str, torch.Tensor]:
    """Deform to ``t0`` and chain integration steps of at most one frame interval to ``t`` (forward or
    back), leaving the Gaussians that hold still at their ``t0`` state.

    ``moving`` [N] bool: the Gaussians above the freeze threshold (default: from ``state``); the still
    codes of ``still.py`` then apply on top of it. With ``extrapolation.hold_surface`` a Gaussian that
    paints a still surface holds still (``surface_painters="hold"``) or stops at the first step that
    would take it off that surface (``"edge"``). ``start``:
    ``model.deform(t0)`` where the caller has it.
    """
    cfg = model.cfg
    gaussians = model.deform(t0) if start is None else start
    means, quats = gaussians["means"], quat_normalize(gaussians["quats"])
    params = model.query_dynamics(means, t0)
    moving = moving_after_handover(model, state, t0, means, params, moving)
    surface = None
    if cfg.extrapolation.hold_surface and moving is not None and t > t0:
        surface = _surface_painters(model, state, means, moving)
        if surface is not None and cfg.extrapolation.surface_painters == "hold":
            moving = moving.clone()
            moving[surface.rows] = False  # held at their t0 state below
            surface = None
        stopped = torch.zeros_like(moving)  # painters stopped so far ("edge")
    span = t - t0
    n = num_substeps(span, model.dt_max) if span else 0
    h = span / max(n, 1)
    # f_trd is queried once, at t0, and its constant accelerations evolve the parameters between steps
    # (``integrate``); without the physics derivation (ablation (4)) it is queried at every step's end.
    requery = not cfg.stage2.physics_derivation
    new_means, new_quats = means, quats
    for k in range(n):
        s = t0 + k * h
        if requery:
            params = model.query_dynamics(new_means, s + h)
        next_means, next_quats, evolved = step(new_means, new_quats, params, h, cfg.stage2.integrator)
        params = params if requery else evolved
        if surface is not None:  # stopped where they would leave their surface
            stopped[surface.rows] |= surface.off(next_means[surface.rows])
            next_means = torch.where(stopped[:, None], new_means, next_means)
            next_quats = torch.where(stopped[:, None], new_quats, next_quats)
        new_means, new_quats = next_means, next_quats
    if moving is not None:
        new_means = torch.where(moving[:, None], new_means, means)
        new_quats = torch.where(moving[:, None], new_quats, quats)
    return {"means": new_means, "quats": new_quats, "scales": gaussians["scales"]}


def _surface_painters(
    model, state: ExtrapolationState, means: torch.Tensor, moving: torch.Tensor
) -> SurfacePainters | None:
    """The surface painters of this handover state (``SurfacePainters.find``), kept in ``state.cache``
    for the next call with the same state (every rendered time after the handover)."""
    settings = model.cfg.extrapolation
    key = (settings.surface_still_fraction, settings.surface_neighbours)
    cached = state.cache.get("surface")
    if (
        cached is not None
        and cached[3] == key
        and cached[0].device == means.device
        and torch.equal(cached[0], means)
        and torch.equal(cached[1], moving)
    ):
        return cached[2]
    painters = SurfacePainters.find(means, moving, *key)
    state.cache["surface"] = (means, moving, painters, key)
    return painters
