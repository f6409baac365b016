"""What the Gaussians of a trained run are clustered on: the paper's physics features (Section 4.3) or
the DefGS baseline's scene flow, the static group, and the trajectories ``--auto-k`` fits.

N: Gaussians, S: sampled times, F: feature columns.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .config import SegmentConfig


@dataclass
class MotionFeatures:
    """The inputs of the clustering, as numpy arrays."""

    groups: dict[str, np.ndarray]
    """Feature groups by name, each [N, F_g] (normalised and weighted together by ``cluster.py``)."""
    weights: dict[str, float]
    positions: np.ndarray
    """[N, 3] the Gaussians at the feature time (the neighbour graph of the label smoothing)."""
    static: np.ndarray
    """[N] bool: the Gaussians that do not move over the training span (one segment of their own)."""
    trajectories: np.ndarray
    """[S, N, 3] f_defo's positions at S times over the training span."""
    velocities: np.ndarray
    """[N, 3] each Gaussian's velocity at the feature time (f_trd's v_bar + w x x; for the flow
    features f_defo's over the last sampled interval): the rigid fits of auto-K."""
    opacity: np.ndarray
    """[N] each Gaussian's opacity (how much it shows: the weight of the rigid fits)."""
    time: float
    """The time the features were taken at (the run's last training time)."""
    static_threshold: float


class SegmentError(ValueError):
    """A run that cannot be segmented as asked (e.g. physics features of a run without f_trd)."""


@torch.no_grad()
def motion_features(predictor, settings: SegmentConfig, extent: float = 1.0) -> MotionFeatures:
    """Deform the canonical Gaussians to the last training time with f_defo, query f_trd there and build
    the features of ``settings.features``; the static group from f_defo's displacements. ``extent``:
    the scene extent of the training cameras, the unit of ``stage2.static_displacement``.
    ``predictor``: the trained run (``extrapolate.Predictor``)."""
    model, state = predictor.model, predictor.state
    if model.deformation is None:
        raise SegmentError("the run has no f_defo (a static or 'no f_defo' run): nothing tells what moves")
    t = float(state.t_max)
    samples = max(2, settings.flow_times)
    times = [t * k / (samples - 1) for k in range(samples)]
    deformed = model.deform_many(times)
    traj = torch.stack([d["means"].float() for d in deformed]).cpu()  # [S, N, 3]
    x = traj[-1]
    moved = (traj - traj[:1]).norm(dim=-1).amax(0)  # f_defo's largest displacement from t = 0
    threshold = settings.static_displacement
    if threshold is None:
        threshold = state.freeze_threshold or model.stage2.static_displacement * extent
    static = moved <= threshold
    if model.static_mask is not None:
        static |= model.static_mask.cpu()
    w = settings
    if w.features == "physics":
        if model.dynamics is None:
            raise SegmentError("the run has no f_trd (a DefGS run): segment it with --settings.features flow")
        params = model.query_dynamics(x.to(model.aabb.device), t)
        v_bar, omega = params.velocity.float().cpu(), params.angular_velocity.float().cpu()
        velocities = v_bar + torch.cross(omega, x, dim=-1)
        if w.twist_neighbours > 0:  # the rigid motion of each Gaussian's neighbourhood
            opacity = torch.sigmoid(model.gaussians["opacities"].detach().float()).cpu()
            v_bar, omega = local_twist(x.double(), velocities.double(), opacity.double(), w.twist_neighbours)
        groups, weights = physics_groups(v_bar, omega, static, w)
    else:
        groups, weights = flow_groups(traj)
        velocities = (traj[-1] - traj[-2]) / (times[-1] - times[-2])
    if w.position_weight > 0:
        groups["position"], weights["position"] = x, w.position_weight
    return MotionFeatures(
        {k: g.double().numpy() for k, g in groups.items()},
        weights,
        x.double().numpy(),
        static.numpy(),
        traj.double().numpy(),
        velocities.double().numpy(),
        torch.sigmoid(model.gaussians["opacities"].detach().float()).cpu().double().numpy(),
        t,
        float(threshold),
    )


def physics_groups(
    velocity: torch.Tensor, angular_velocity: torch.Tensor, static: torch.Tensor, settings: SegmentConfig
) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """The paper's feature groups (|v_bar|, v_bar, |w|, w/|w|) of f_trd's ``velocity`` (v_bar) and
    ``angular_velocity`` (w) [N, 3], and their weights; the axis is damped where the spin is small
    (``SegmentConfig.axis_floor``), measured on the Gaussians not ``static`` [N]."""
    spin = angular_velocity.norm(dim=-1, keepdim=True)
    moving = ~static
    reference = float(spin[moving].quantile(0.9)) if bool(moving.any()) else 0.0
    axis = angular_velocity / torch.clamp(spin, min=max(reference * settings.axis_floor, 1e-9))
    groups = {"speed": velocity.norm(dim=-1, keepdim=True), "velocity": velocity, "spin": spin, "axis": axis}
    weights = {
        "speed": settings.speed_weight,
        "velocity": settings.velocity_weight,
        "spin": settings.spin_weight,
        "axis": settings.axis_weight,
    }
    return groups, weights


def flow_groups(trajectories: torch.Tensor) -> tuple[dict[str, torch.Tensor], dict[str, float]]:
    """The baseline's one feature group: each Gaussian's f_defo displacements from the first sampled
    time to every later one, trajectories [S, N, 3] -> [N, 3 (S - 1)]."""
    flow = (trajectories[1:] - trajectories[:1]).permute(1, 0, 2).reshape(trajectories.shape[1], -1)
    return {"flow": flow}, {"flow": 1.0}


def local_twist(
    x: torch.Tensor, u: torch.Tensor, weights: torch.Tensor, neighbours: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """(v_bar [N, 3], w [N, 3]): the rigid motion (u = v_bar + w x x) that best explains the velocities
    ``u`` [N, 3] of each point's ``neighbours`` nearest points ``x`` [N, 3] (itself included), by
    least squares weighted by ``weights`` [N] (a little ridge keeps flat patches solvable)."""
    from scipy.spatial import cKDTree

    k = min(neighbours, len(x))
    if k < 3:
        return u.clone(), torch.zeros_like(u)
    _, nn = cKDTree(x.numpy()).query(x.numpy(), k)
    nn = torch.as_tensor(nn).reshape(len(x), k)
    xn, un, wn = x[nn], u[nn], weights[nn]  # [N, k, 3], [N, k, 3], [N, k]
    wn = wn.clamp_min(1e-6)
    centre = (xn * wn[..., None]).sum(1) / wn.sum(1, keepdim=True)
    d = xn - centre[:, None]
    a = twist_design(d)
    a = a.reshape(len(x), -1, 6)
    w3 = wn.repeat_interleave(3, dim=1)
    ata = torch.einsum("nki,nk,nkj->nij", a, w3, a)
    atb = torch.einsum("nki,nk,nk->ni", a, w3, un.reshape(len(x), -1))
    ridge = 1e-6 * ata.diagonal(dim1=1, dim2=2).sum(-1)[:, None, None] * torch.eye(6, dtype=x.dtype)
    sol = torch.linalg.solve(ata + ridge, atb[..., None])[..., 0]
    v_centre, omega = sol[:, :3], sol[:, 3:]
    return (v_centre - torch.cross(omega, centre, dim=-1)).float(), omega.float()


def twist_design(d: torch.Tensor) -> torch.Tensor:
    """[..., 3, 6] the linear map from a twist (V, W) to the velocity V + W x d of offsets ``d`` [..., 3]."""
    zero = torch.zeros_like(d[..., 0])
    a = torch.zeros(*d.shape[:-1], 3, 6, dtype=d.dtype)
    a[..., :3] = torch.eye(3, dtype=d.dtype)
    a[..., 3:] = torch.stack(
        [torch.stack([zero, d[..., 2], -d[..., 1]], -1), torch.stack([-d[..., 2], zero, d[..., 0]], -1),
         torch.stack([d[..., 1], -d[..., 0], zero], -1)], -2,
    )  # fmt: skip
    return a
