"""Learned dynamics of a trained TRACE run against its synthetic scene's ground-truth parts.

Prints, for each ground-truth part (Gaussians within 0.03 of its surface) at a few training times and
at the handover, the median learned particle velocity, equivalent acceleration a_bar, angular velocity
w and angular acceleration eps, the acceleration that f_trd's own velocities imply along the motion
(``a_fd``: the change of v_bar from (x_t, t) to the integrated (x_t+dt, t + dt), dt = 2 frames, over dt,
the target of ``dynamic.acceleration_consistency``), the angular velocity of the rigid motion that best
fits f_defo's own motion of the part's Gaussians over the same dt (``w_defo``, Kabsch via scipy: what
the deformation field has reconstructed, for telling a physics error from a reconstruction error),
and the mean |weight| of f_trd's acceleration head (its init is N(0, 0.01^2)).
Usage: .venv/bin/python benchmarks/learned_dynamics.py RUN [RUN ...]
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from tracegs.eval.physics import _gt, _parts_at
from tracegs.physics.integrate import integrate, particle_velocity
from tracegs.train.trainer import load_run


def _rigid_fit_angular_velocity(a: torch.Tensor, b: torch.Tensor, dt: float) -> np.ndarray:
    """Angular velocity (rotation vector / dt) of the rotation that best maps the centred points a to b."""
    a, b = (p.double().numpy() for p in (a, b))
    rotation, _ = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))
    return (rotation.as_rotvec() / dt).round(4)


def _median(x: torch.Tensor):
    return x.median(0).values.numpy().round(4)


@torch.no_grad()
def report(run: Path) -> None:
    model, cfg, meta = load_run(run, device="cpu")
    t_max, gt = meta["t_max"], _gt(Path(cfg.data))
    if model.dynamics is None:  # DefGS: f_defo's own motion only
        print(f"{run}: no f_trd (DefGS)")
    else:
        head = model.dynamics.head.weight[model.dynamics.slices["acceleration"]]
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


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    for run in ap.parse_args().runs:
        report(run)
