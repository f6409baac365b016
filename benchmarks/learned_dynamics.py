"""Learned dynamics of a trained TRACE run against its synthetic scene's ground-truth parts.

Prints, for each ground-truth part (Gaussians within 0.03 of its surface) at a few training times and
at the handover, the median learned particle velocity, equivalent acceleration a_bar, angular velocity
w and angular acceleration eps, the acceleration that f_trd's own velocities imply along the motion
(``a_fd``: the change of v_bar from (x_t, t) to the integrated (x_t+dt, t + dt), dt = 2 frames, over dt,
the target of ``dynamic.acceleration_consistency``), the angular velocity of the rigid motion that best
fits f_defo's own motion of the part's Gaussians over the same dt (``w_defo``, Kabsch via scipy: what
the deformation field has reconstructed, for telling a physics error from a reconstruction error),
and the mean |weight| of f_trd's acceleration head (its init is N(0, 0.01^2)).
A "rigid fit" line per part and time reads the part as one rigid body, independently of how each
particle's velocity is split between v_bar and w: the rigid motion that best fits the particle
velocities ``v_bar + w x x`` (the velocity of the part's moving pivot, and w), and the pivot's
acceleration that the learned accelerations give (``a_bar + eps x x + w x u`` fitted with a rigid
acceleration field), each beside the closed-form truth.
Usage: .venv/bin/python benchmarks/learned_dynamics.py RUN [RUN ...]
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from tracegs.eval.physics import _gt, _motions, _parts_at
from tracegs.physics.integrate import integrate, particle_velocity
from tracegs.physics.so3 import skew
from tracegs.train.trainer import load_run


def _rigid_fit_angular_velocity(a: torch.Tensor, b: torch.Tensor, dt: float) -> np.ndarray:
    """Angular velocity (rotation vector / dt) of the rotation that best maps the centred points a to b."""
    a, b = (p.double().numpy() for p in (a, b))
    rotation, _ = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))
    return (rotation.as_rotvec() / dt).round(4)


def _rigid_fit(x: torch.Tensor, u: torch.Tensor, acc: torch.Tensor, pivot: torch.Tensor):
    """Least-squares rigid motion of particles at ``x`` with velocities ``u``: ``u = v + w x (x - pivot)``
    gives (v, w); then ``acc - w x (w x r) = a + eps x r`` gives the pivot's acceleration a."""
    r = (x - pivot).double()
    system = torch.cat([torch.eye(3, dtype=r.dtype).expand(len(r), 3, 3), -skew(r)], -1).reshape(-1, 6)
    v_w = torch.linalg.lstsq(system, u.double().reshape(-1)).solution
    w = v_w[3:].expand_as(r)
    centripetal = torch.cross(w, torch.cross(w, r, dim=-1), dim=-1)
    a_eps = torch.linalg.lstsq(system, (acc.double() - centripetal).reshape(-1)).solution
    return v_w[:3].numpy().round(3), v_w[3:].numpy().round(3), a_eps[:3].numpy().round(3)


def _truth(motion: dict, t: float):
    """(pivot at t, its velocity, its acceleration, w) of a part's closed-form motion (gt/motion.json)."""
    v, a = np.asarray(motion["linear_velocity"]), np.asarray(motion["linear_acceleration"])
    pivot = np.asarray(motion["pivot"]) + v * t + 0.5 * a * t * t
    w = (motion["angular_velocity"] + motion["angular_acceleration"] * t) * np.asarray(motion["axis"])
    return pivot, (v + a * t).round(3), a.round(3), w.round(3)


def _median(x: torch.Tensor):
    return x.median(0).values.numpy().round(4)


@torch.no_grad()
def report(run: Path) -> None:
    model, cfg, meta = load_run(run, device="cpu")
    t_max, gt, motions = meta["t_max"], _gt(Path(cfg.data)), _motions(Path(cfg.data))
    if model.dynamics is None:  # DefGS: f_defo's own motion only
        print(f"{run}: no f_trd (DefGS)")
    else:
        field = model.dynamics
        own = "acceleration" in field.own_names  # from the accelerations' own MLP
        head = (field.acceleration_head if own else field.head).weight[field.head_rows("acceleration")]
        print(f"{run}: acceleration head mean |w| {head.abs().mean().item():.4f}")
    for t in (0.2, 0.4, 0.6, model.handover_time(t_max)):
        means, owner = _parts_at(model, t, t_max, gt, 0.03)
        dt = 2 * model.dt_max
        defo_later = model.deform(t + dt)["means"]
        if model.dynamics is not None:
            p = model.query_dynamics(means, t)
            later = integrate(means, model.deform(t)["quats"], p, dt, model.dt_max)[0]
            a_fd = (model.query_dynamics(later, t + dt).velocity - p.velocity) / dt
        for part in sorted(set(owner.tolist()) - {0}):
            m = owner == part
            line = f"  t={t:.3f} part {part}:"
            if model.dynamics is not None:
                v = particle_velocity(means[m], p.velocity[m], p.angular_velocity[m])
                a_bar, w, eps = (
                    _median(x[m]) for x in (p.acceleration, p.angular_velocity, p.angular_acceleration)
                )
                line += f" v {_median(v)} a_bar {a_bar} a_fd {_median(a_fd[m])} w {w} eps {eps}"
            print(f"{line} w_defo {_rigid_fit_angular_velocity(means[m], defo_later[m], dt)}")
            if model.dynamics is not None:
                pivot, v_true, a_true, w_true = _truth(motions[part - 1], t)
                x = means[m]
                acc = (
                    p.acceleration[m]
                    + torch.cross(p.angular_acceleration[m], x, dim=-1)
                    + torch.cross(p.angular_velocity[m], v, dim=-1)
                )
                v_fit, w_fit, a_fit = _rigid_fit(x, v, acc, torch.as_tensor(pivot, dtype=x.dtype))
                print(
                    f"  t={t:.3f} part {part} rigid fit: pivot v {v_fit} (true {v_true}) w {w_fit} "
                    f"(true {w_true}) pivot a from the accelerations {a_fit} (true {a_true})"
                )


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    for run in ap.parse_args().runs:
        report(run)
