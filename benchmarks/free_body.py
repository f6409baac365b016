"""Would a free-body extrapolation of each moving part do better than the learned physics? A diagnosis
on synthetic scenes (``gt/`` of `tracegs synth`); docs/PHYSICS.md, "A free body per part".

After the handover, the Gaussians of each moving part are moved as one rigid body: a pivot follows
the parabola fitted to its path under f_defo over the ``--window`` frames before the handover (a
constant acceleration, as gravity gives a free body), and the body turns about it at a constant
angular velocity: f_trd's, read as the rigid motion that best fits the part's particle velocities
``v_bar + w x x`` at the handover (``--spin trd``), or f_defo's own turn over the last two frames
(``--spin defo``). Every other Gaussian keeps its learned future.

- ``--pivot centroid``: the part's centroid; ``fitted``: the body point whose path under f_defo is
  closest to a parabola (for a hinge, a point of its axis).
- ``--parts-from truth``: the ground-truth parts (each Gaussian to the nearest, as in
  ``oracle_motion.py``); ``rigid``: found without labels, as the connected groups of moving
  neighbours whose f_trd velocities keep their distances (``_rigid_components``); ``kmeans``, K-means
  over f_trd's particle velocities and spins, K the number of moving ground-truth parts.
- ``--backtest K``: a part is given the free body only if it passes a test over the K frames before
  the handover: ``points`` / ``centroid``, the free body fitted K frames earlier predicts f_defo's
  Gaussians / their centroid at the handover better than the learned physics from there; ``axis``,
  the part turns (|w| > 0.2) about an axis that moved by 0.03 or more (a part whose axis stays is a
  hinge, which the learned physics holds by construction). It also prints, as a diagnosis, how far
  the axis moved from where a free body's would have moved (``_free_axis_shift``); ``images``, each
  model from K frames before the handover, rendered with the part moved by it (every other Gaussian
  where f_defo puts it) into the training cameras at the training frames from there to t_max, the one
  nearer the training images (mean squared error) kept: a test on the data, which (unlike f_defo's
  state) sees the part's spin.

A spinning body that falls is what the learned physics cannot hold: its equivalent acceleration
a_bar changes at -w x a_c (docs/PHYSICS.md, "What the physics costs").

Usage: .venv/bin/python benchmarks/free_body.py [--future-end 0.7627] [options] RUN ...
RUN: a validation run, scored to ``--future-end``; without it the test split is scored (a diagnosis
of a finished run, never a way to choose a setting).
"""

import argparse
from pathlib import Path

import numpy as np
import torch
from oracle_motion import score_replaced
from scipy.spatial.transform import Rotation

from tracegs.eval.physics import _gt, _motions, _parts_at
from tracegs.physics.free_body import FreeBody, fit_parabola, fit_rigid_velocity, move, rigid_components
from tracegs.physics.integrate import particle_velocity
from tracegs.physics.so3 import quat_normalize
from tracegs.train.calibrate import _Backtest


def _moves(motion: dict) -> bool:
    keys = ("linear_velocity", "linear_acceleration", "angular_velocity", "angular_acceleration")
    return any(np.abs(np.asarray(motion[k], dtype=float)).max() > 0 for k in keys)


def _pivot_path(times: np.ndarray, past: list[np.ndarray], t0: float, ridge: float = 1e-2):
    """(p, v, a): the body point ``p`` (at ``t0``) whose path over the window is closest to a parabola
    ``p + v s + a s^2 / 2``, and that parabola. Each frame's rigid map ``x -> R_k x + T_k`` from the
    points at ``t0`` (``past[0]``) is a Kabsch fit; ``(R_k - I) p - v s_k - a s_k^2 / 2 = -T_k`` is linear
    in (p, v, a). A body that only translates leaves p free: a small ridge pulls it to the centroid."""
    x0 = past[0]
    mean0 = x0.mean(0)
    rows, rhs = [], []
    for t, xk in zip(times, past, strict=True):
        rotation, _ = Rotation.align_vectors(xk - xk.mean(0), x0 - mean0)
        r = rotation.as_matrix()
        shift = xk.mean(0) - r @ mean0
        s = t - t0
        rows.append(np.concatenate([r - np.eye(3), -s * np.eye(3), -0.5 * s * s * np.eye(3)], 1))
        rhs.append(-shift)
    rows.append(np.concatenate([ridge * np.eye(3), np.zeros((3, 6))], 1))
    rhs.append(ridge * mean0)
    sol = np.linalg.lstsq(np.concatenate(rows), np.concatenate(rhs), rcond=None)[0]
    return sol[:3], sol[3:6], sol[6:9]


def _rigid_components(
    model, means: torch.Tensor, t0: float, window: int, moved: float = 0.01
) -> torch.Tensor:
    """[N] label of each Gaussian's rigid body, found without labels (0: none): the Gaussians f_defo
    moved by more than ``moved`` over the window, grouped by f_trd's velocities (``rigid_components``
    of ``tracegs.physics.free_body``)."""
    before = model.deform(max(0.0, t0 - window * model.dt_max))["means"]
    labels = rigid_components(
        means, (means - before).norm(dim=-1) > moved, _f_trd_velocities(model, means, t0), speed_floor=0.01
    )
    print(f"  rigid bodies: {int(labels.max())} of sizes {torch.bincount(labels)[1:].tolist()}")
    return labels


def _rigid_velocity_fit(x: torch.Tensor, u: torch.Tensor, pivot) -> tuple[np.ndarray, ...]:
    """(v, w) of the rigid motion ``u = v + w x (x - pivot)`` that best fits the particle velocities."""
    return tuple(z.numpy() for z in fit_rigid_velocity(x, u, torch.as_tensor(pivot)))


def _f_trd_velocities(model, x: torch.Tensor, t: float) -> torch.Tensor:
    params = model.query_dynamics(x, t)
    return particle_velocity(x, params.velocity, params.angular_velocity)


def _kmeans_parts(model, means: torch.Tensor, t0: float, window: int, k: int, moved: float = 0.01):
    """[N] part label (0: none) of the Gaussians f_defo moved by more than ``moved`` over the window:
    K-means (scikit-learn) over f_trd's particle velocity and angular velocity at ``t0``, the paper's
    segmentation by the learned physics, with ``k`` the number of moving ground-truth parts."""
    from sklearn.cluster import KMeans

    before = model.deform(max(0.0, t0 - window * model.dt_max))["means"]
    idx = torch.nonzero((means - before).norm(dim=-1) > moved).squeeze(1)
    params = model.query_dynamics(means[idx], t0)
    u = particle_velocity(means[idx], params.velocity, params.angular_velocity)
    features = torch.cat([u, params.angular_velocity], 1).double().numpy()
    labels = torch.zeros(len(means), dtype=torch.long)
    if len(idx) >= k:
        labels[idx] = torch.as_tensor(KMeans(k, n_init=10, random_state=0).fit_predict(features)).long() + 1
    print(f"  k-means parts: sizes {torch.bincount(labels)[1:].tolist()}")
    return labels


def _axis(model, x: torch.Tensor, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(point of the instantaneous rotation axis nearest the centroid, w) of the rigid motion that best
    fits f_trd's particle velocities at ``x``, time ``t``."""
    c = x.double().mean(0)
    v, w = _rigid_velocity_fit(x, _f_trd_velocities(model, x, t), c)
    return c.numpy() + np.cross(w, v) / max(float(w @ w), 1e-12), w


def _free_axis_shift(v, a, w, span: float) -> np.ndarray:
    """How the instantaneous axis of a free body (pivot on the parabola ``c0 + v s + a s^2 / 2``,
    constant spin ``w``) moves over the ``span`` before ``s = 0``: the axis point nearest the pivot is
    ``c + w x v_c / |w|^2`` (as in ``_axis``), and only ``c`` and ``v_c`` change."""
    return v * span - 0.5 * a * span**2 + np.cross(w, a * span) / max(float(w @ w), 1e-12)


def _spin_from_positions(a: torch.Tensor, b: torch.Tensor, dt: float) -> np.ndarray:
    """w of the rotation that best maps the centred points ``a`` to ``b`` over ``dt`` (Kabsch)."""
    a, b = (p.double().numpy() for p in (a, b))
    rotation, _ = Rotation.align_vectors(b - b.mean(0), a - a.mean(0))
    return rotation.as_rotvec() / dt


def _move(
    means: torch.Tensor, quats: torch.Tensor, c0, v, a, w, s: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussians of a free body (``tracegs.physics.free_body.move``), ``s`` after ``c0``'s time."""
    body = FreeBody(*(torch.as_tensor(z, dtype=torch.float64) for z in (c0, v, a, w)))
    return move(means, quats, body, s)


def _gap(x: torch.Tensor, ref: torch.Tensor, on: str) -> float:
    """Mean distance of the points (``on="points"``) or distance of their centroids (``"centroid"``)."""
    if on == "centroid":
        return (x.mean(0) - ref.mean(0)).norm().item()
    return (x - ref).norm(dim=-1).mean().item()


def with_free_body_motion(
    model,
    data: Path,
    window: int,
    spin: str,
    backtest: int = 0,
    backtest_on: str = "points",
    pivot: str = "centroid",
    parts_from: str = "truth",
):
    """Replace ``model.state_at`` after the handover by each moving part's free-body motion (the
    options are the command line's, module docstring)."""
    gt = _gt(data)
    parts = sorted(int(p) for p in np.unique(gt[1]))
    moving = [p for p, m in zip(parts, _motions(data), strict=True) if _moves(m)]
    learned, fits, deformed = model.state_at, {}, {}

    def means_at(t: float) -> torch.Tensor:
        """f_defo's means at ``t``, deformed once for every part that reads them."""
        if t not in deformed:
            deformed[t] = model.deform(t)["means"]
        return deformed[t]

    def free_body(t0: float, rows: torch.Tensor) -> tuple[np.ndarray, ...]:
        """(c0, v, a, w) of the Gaussians ``rows`` fitted at ``t0`` from the frames before it."""
        times = np.array([max(0.0, t0 - k * model.dt_max) for k in range(window + 1)])
        past = [means_at(float(t))[rows] for t in times]
        if pivot == "fitted":
            c0, v, a = _pivot_path(times, [m.double().numpy() for m in past], t0)
        else:
            centroids = torch.stack([m.double().mean(0) for m in past])
            c0, v, a = (z.numpy() for z in fit_parabola(torch.as_tensor(times), centroids, t0))
        if spin == "defo":
            return c0, v, a, _spin_from_positions(past[2], past[0], 2 * model.dt_max)
        u = _f_trd_velocities(model, past[0], t0)
        return c0, v, a, _rigid_velocity_fit(past[0], u, c0)[1]

    def fit(t0: float, t_max: float) -> None:
        state = model.deform(t0)
        if parts_from == "rigid":
            owner = _rigid_components(model, state["means"], t0, window)
            chosen = sorted(set(owner.tolist()) - {0})
        elif parts_from == "kmeans":
            owner = _kmeans_parts(model, state["means"], t0, window, len(moving))
            chosen = sorted(set(owner.tolist()) - {0})
        else:
            owner, chosen = _parts_at(model, t0, t_max, gt, float("inf"))[1], moving
        fits.update(state=state, rows={}, motion={})
        t1 = t0 - backtest * model.dt_max
        if backtest and backtest_on == "images":
            photo = _Backtest(model, data, model.cfg.downscale, t1, t_max)
        elif backtest:
            x1 = means_at(t1)
            learned_then = None if backtest_on == "axis" else model._physics_from(t1, t0)["means"]
        for p in chosen:
            rows = owner == p
            if int(rows.sum()) < 3:
                continue
            motion = free_body(t0, rows)
            if backtest and backtest_on == "axis":  # a hinge keeps its axis where it is: learned physics
                (q0, w0), (q1, _) = (_axis(model, m[rows], t) for m, t in ((state["means"], t0), (x1, t1)))
                shift = float(np.linalg.norm(q0 - q1))
                hinge = np.linalg.norm(w0) > 0.2 and shift < 0.03
                expected = _free_axis_shift(*motion[1:], t0 - t1)
                print(
                    f"  part {p}: a free body's axis would have moved {np.linalg.norm(expected):.4f}, "
                    f"off the one seen by {np.linalg.norm(q0 - q1 - expected):.4f}"
                )
                print(
                    f"  part {p}: |w| {np.linalg.norm(w0):.3f}, axis moved {shift:.4f} over {backtest} frames: {'hinge' if hinge else 'free'}"
                )
                if hinge:
                    continue
            elif backtest and backtest_on == "images":
                body = FreeBody(*(torch.as_tensor(z, dtype=torch.float64) for z in free_body(t1, rows)))
                err_learned, err_free = photo.error(rows, None), photo.error(rows, body)
                print(
                    f"  part {p} ({int(rows.sum())} Gaussians): image backtest over {len(photo.views)} frames, "
                    f"mse learned {err_learned:.3e}, free body {err_free:.3e}"
                )
                if err_learned <= err_free:
                    continue
            elif backtest:  # each model predicts t0 from t1; f_defo's state at t0 is the reference
                c1, v, a, w = free_body(t1, rows)
                free_then = _move(x1[rows], model.deform(t1)["quats"][rows], c1, v, a, w, t0 - t1)[0]
                ref = state["means"][rows]
                err_free, err_learned = (_gap(x, ref, backtest_on) for x in (free_then, learned_then[rows]))
                print(
                    f"  part {p}: backtest over {backtest} frames ({backtest_on}), learned {err_learned:.4f}, free body {err_free:.4f}"
                )
                if err_learned <= err_free:
                    continue
            fits["rows"][p], fits["motion"][p] = rows, motion

    def state_at(t: float, t_max: float) -> dict[str, torch.Tensor]:
        t0 = model.handover_time(t_max)
        if t <= t0:
            return learned(t, t_max)
        if not fits:
            fit(t0, t_max)
        future, start, s = learned(t, t_max), fits["state"], t - t0
        means, quats = future["means"].clone(), quat_normalize(future["quats"]).clone()
        for p, rows in fits["rows"].items():
            c0, v, a, w = fits["motion"][p]
            means[rows], quats[rows] = _move(start["means"][rows], start["quats"][rows], c0, v, a, w, s)
        return {"means": means, "quats": quats, "scales": start["scales"]}

    model.state_at = state_at
    return model


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument(
        "--future-end", type=float, default=None, help="validation future's end (default: test split)"
    )
    ap.add_argument(
        "--window", type=int, default=12, help="frames before the handover for the centroid's fit"
    )
    ap.add_argument("--backtest", type=int, default=0, help="choose per part by a backtest over these frames")
    ap.add_argument("--pivot", choices=("centroid", "fitted"), default="centroid", help="the body's pivot")
    ap.add_argument(
        "--parts-from",
        choices=("truth", "rigid", "kmeans"),
        default="truth",
        help="parts: ground truth or found",
    )
    ap.add_argument(
        "--backtest-on",
        choices=("points", "centroid", "axis", "images"),
        default="points",
        help="backtest gap",
    )
    ap.add_argument(
        "--spin", choices=("trd", "defo"), default="trd", help="angular velocity from f_trd or f_defo"
    )
    args = ap.parse_args()
    settings = (args.window, args.spin, args.backtest, args.backtest_on, args.pivot, args.parts_from)
    for run in args.runs:
        learned, free, parts = score_replaced(
            run, args.future_end, lambda model, data: with_free_body_motion(model, data, *settings)
        )
        print(
            f"{run.name}: learned {learned['psnr']:.3f} dB (MAE-PSNR {learned['mae_psnr']:.3f}), free body "
            f"(parts {args.parts_from}, pivot {args.pivot}, spin {args.spin}, window {args.window}, backtest {args.backtest} on {args.backtest_on}) {free['psnr']:.3f} ({free['mae_psnr']:.3f}); parts {parts}"
        )


if __name__ == "__main__":
    main()
