"""The parts of a trained model that move as free bodies after the handover
(``extrapolation.free_bodies``): the rigid groups of moving Gaussians that touch nothing still (split
into their rigid parts where they have parts on hinges), and whose free body (``physics/free_body.py``),
fitted to the training images (``refine_free_body``), predicts the last training images in a backtest
from before the handover about as well as the learned physics or better.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from ..image_metrics import mse
from ..physics.free_body import (
    FREE_BODY_NUMBERS,
    FreeBody,
    centre_of_mass,
    fit_parabola,
    fit_rigid_velocity,
    isolation,
    main_piece,
    median_spacing,
    move,
    pivot_path,
    rigid_components,
    split_rigid,
)
from ..physics.integrate import particle_velocity
from .views import TrainingViews


class _Backtest(TrainingViews):
    """Futures started at ``t1`` against the training images at the training times in (``t1``, ``t_max``]:
    one part's Gaussians moved by a candidate motion, every other Gaussian where f_defo puts it."""

    def __init__(self, predictor, data: Path, downscale: int, t1: float, t_max: float):
        super().__init__(predictor.model, data, downscale, t1, t_max, t_max)
        self.t1 = t1
        self.start = predictor.model.deform(t1)
        self.learned = {t: predictor.physics_from(t1, t) for t in self.views}

    def error(self, rows: torch.Tensor, body: FreeBody | None) -> float:
        """Mean squared error over the views with the Gaussians ``rows`` moved from ``t1`` by ``body``
        (None: the learned physics)."""
        errors = []
        for t, views in self.views.items():
            if body is None:
                part = self.learned[t]["means"][rows], self.learned[t]["quats"][rows]
            else:
                part = move(self.start["means"][rows], self.start["quats"][rows], body, t - self.t1)
            state = self.with_part(t, rows, *part)
            for camera, gt in views:
                errors.append(float(mse(self.render(state, camera).clamp(0, 1), gt)))
        return sum(errors) / max(len(errors), 1)


def window_means(model, t0: float, window: int) -> tuple[torch.Tensor, list[torch.Tensor]]:
    """(times, f_defo's means at each): ``t0`` and the ``window`` frames before it (clamped at 0),
    deformed once for every part fitted there."""
    times = torch.tensor([max(0.0, t0 - k * model.dt_max) for k in range(window + 1)], dtype=torch.float64)
    return times, [model.deform(float(t))["means"] for t in times]


def moving_groups(predictor, t0: float, extent: float, window: int) -> tuple:
    """``(path, moved, u, groups)``: f_defo's means over the ``window`` frames before ``t0``
    (``window_means``), the [N] bool Gaussians it moves by more than 0.25% of the scene ``extent`` over
    them, f_trd's particle velocities [N, 3] at ``t0``, and the [N] labels of the rigid groups of the
    moved ones (``rigid_components``; 0: none). Free bodies and joint parts are found among them, so
    the result is kept in the state's cache for the calibration's next call."""
    model, state = predictor.model, predictor.state
    key = (t0, extent, window, model.gaussians["means"].shape[0])
    cached = state.cache.get("moving_groups")
    if cached is not None and cached[0] == key:
        return cached[1]
    path = window_means(model, t0, window)
    x0, before = path[1][0], path[1][-1]
    moved = (x0 - before).norm(dim=-1) > 0.0025 * extent
    params = model.query_dynamics(x0, t0)
    u = particle_velocity(x0, params.velocity, params.angular_velocity)
    groups = path, moved, u, rigid_components(x0, moved, u, 0.0025 * extent).to(x0.device)
    state.cache["moving_groups"] = (key, groups)
    return groups


def fit_free_body(
    model, rows: torch.Tensor, t0: float, path: tuple[torch.Tensor, list[torch.Tensor]]
) -> FreeBody:
    """The free body of the Gaussians ``rows`` at ``t0``: its pivot, the centre of mass at ``t0`` of
    their main piece (``centre_of_mass``, ``main_piece``); the pivot's parabola fitted to its path under f_defo's rigid motion of them
    over the window ``path`` (``window_means``; ``pivot_path``); its spin the rigid motion that best
    fits f_trd's particle velocities over them at ``t0``."""
    times, past = path
    x = past[0][rows]
    c0 = centre_of_mass(x[main_piece(x).to(x.device)])
    _, v, a = fit_parabola(times, pivot_path(c0, x, [means[rows] for means in past]), t0)
    params = model.query_dynamics(x, t0)
    _, w = fit_rigid_velocity(x, particle_velocity(x, params.velocity, params.angular_velocity), c0)
    return FreeBody(c0, v, a, w)


def legendre_to_path(lo: float, hi: float, t0: float) -> torch.Tensor:
    """[3, 3] float64: the change of a pivot's (v, a, shift) at ``t0`` (rows) made by adding ``c0 P0(x) +
    c1 P1(x) + c2 P2(x)`` (columns: the Legendre polynomials' coefficients, displacements) to its path
    over ``[lo, hi]`` (``x`` = -1 at ``lo``, 1 at ``hi``)."""
    h, x0 = (hi - lo) / 2, (2 * t0 - lo - hi) / (hi - lo)
    return torch.tensor(
        [[0.0, 1 / h, 3 * x0 / h], [0.0, 0.0, 3 / h**2], [1.0, x0, (3 * x0**2 - 1) / 2]],
        dtype=torch.float64,
    )


def refine_free_body(
    body: FreeBody,
    rows: torch.Tensor,
    start: dict[str, torch.Tensor],
    t0: float,
    frames: TrainingViews,
    steps: int,
    views_per_step: int,
    seed: int = 0,
) -> FreeBody:
    """``body``, the free body of the Gaussians ``rows`` from their state ``start`` at ``t0``, fitted to the
    training images of ``frames``: Adam lowers the L1 error of the images rendered with the part moved
    by the body (every other Gaussian where f_defo puts it), ``views_per_step`` random views a step.

    f_defo's path gives the parabola only roughly (its acceleration on `fallingball` was a quarter
    off), and f_trd's spin at one instant may be off too; the images fix both, a spinning textured
    body's spin best, and where f_defo puts the body at ``t0`` (``shift``). The pivot stays: over a
    window of a few frames the images cannot tell a pivot moved by ``d`` from a velocity and an
    acceleration changed by ``w x d`` and ``w x (w x d)``. The pivot's change of path is stepped as
    three displacements, the coefficients of the Legendre polynomials P0, P1, P2 over the frames'
    span (``legendre_to_path``; orthogonal there, where ``shift``, ``v`` and ``a`` are strongly
    correlated and Adam, diagonal, settles the acceleration slowly), the spin as ``w + dw / (L R)``
    (``L`` the largest time from ``t0`` in the span, ``R`` the part's radius); about a tenth of its
    Gaussian spacing a step at first."""
    pairs = [(t, camera, gt) for t, views in frames.views.items() for camera, gt in views]
    lo, hi = min(frames.views, default=t0), max(frames.views, default=t0)
    span = max(abs(lo - t0), abs(hi - t0))
    if steps <= 0 or hi <= lo or int(rows.sum()) < 2:
        return body
    means, quats = start["means"][rows].detach(), start["quats"][rows].detach()
    points = means.double()
    radius = float((points - points.mean(0)).square().sum(-1).mean().sqrt())
    spacing = median_spacing(points.cpu().numpy())
    base = torch.stack([body.v, body.a, body.w, body.shift])
    unit = torch.zeros(4, 4, dtype=torch.float64)  # rows v, a, w, shift from P0, P1, P2, dw
    unit[[0, 1, 3], :3] = legendre_to_path(lo, hi, t0)
    unit[2, 3] = 1 / (span * max(radius, 1e-9))
    delta = torch.zeros(4, 3, dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([delta], lr=0.1 * max(spacing, 1e-9))
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, steps)
    generator = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        pick = torch.randperm(len(pairs), generator=generator)[:views_per_step].tolist()
        with torch.enable_grad():
            candidate = FreeBody(body.c0, *(base + unit @ delta))
            loss = 0.0
            for i in pick:
                t, camera, gt = pairs[i]
                state = frames.with_part(t, rows, *move(means, quats, candidate, t - t0))
                loss = loss + (frames.render(state, camera) - gt).abs().mean()
            optimizer.zero_grad()
            (loss / len(pick)).backward()
        optimizer.step()
        schedule.step()
    return FreeBody(body.c0, *(base + unit @ delta.detach()))


@torch.no_grad()
def choose_free_bodies(predictor, data: Path, downscale: int, extent: float) -> tuple[dict, list]:
    """The free bodies of a trained model (``extrapolation.free_bodies``): ``({"t0", "labels", "bodies"},
    report)``. The parts are the rigid groups (``rigid_components``) of the Gaussians that f_defo moves
    by more than 0.25% of the scene ``extent`` over the window before the handover t0, by f_trd's
    velocities at t0. A part is free when it lies ``free_body_isolation`` spacings from every still
    Gaussian (``isolation``) and a free body fitted ``free_body_backtest`` frames before t0 predicts the
    training images from there no worse than ``free_body_tolerance`` times the learned physics does.
    ``labels`` [N]: 0 = the learned physics, k = ``bodies[k - 1]`` (``FreeBody.as_tensor`` at t0; [K, 15])."""
    model, dyn, t_max = predictor.model, predictor.settings, predictor.t_max
    t0 = predictor.handover_time()
    dev = model.aabb.device
    none = {
        "t0": t0,
        "labels": torch.zeros(model.gaussians["means"].shape[0], dtype=torch.long, device=dev),
        "bodies": torch.zeros(0, FREE_BODY_NUMBERS, dtype=torch.float64),
    }
    t1 = t0 - dyn.free_body_backtest * model.dt_max
    if t1 - 2 * model.dt_max < -1e-9:  # too early in the span for a parabola before the backtest
        return none, []
    path_t0, moved, u, parts = moving_groups(predictor, t0, extent, dyn.free_body_window)
    x0 = path_t0[1][0]
    backtest = path_t1 = before_t1 = None
    chosen, report = [], []

    def fit_views(t: float, t_to: float) -> TrainingViews | None:
        """The training images a free body from ``t`` is fitted to: its window's, to ``t_to``."""
        if dyn.free_body_refine_steps <= 0:
            return None
        t_from = t - (dyn.free_body_window + 0.5) * model.dt_max
        return TrainingViews(model, data, downscale, t_from, t_to, t_max)

    def refine(body: FreeBody, rows, start, t: float, frames: TrainingViews | None) -> FreeBody:
        if frames is None:
            return body
        steps, views = dyn.free_body_refine_steps, dyn.free_body_refine_views
        return refine_free_body(body, rows, start, t, frames, steps, views)

    for label in range(1, int(parts.max()) + 1):
        group = parts == label
        apart = isolation(x0, group, ~moved)  # inf when nothing is still; JSON (summary.json) says null
        entry = {"gaussians": int(group.sum()), "isolation": apart if math.isfinite(apart) else None}
        if apart <= dyn.free_body_isolation:
            report.append({**entry, "free_body": False})
            continue  # it touches something still: a hinge or a rail, which the learned physics holds
        if backtest is None:
            backtest = _Backtest(predictor, data, downscale, t1, t_max)
            path_t1 = window_means(model, t1, dyn.free_body_window)
            before_t1 = fit_views(t1, t1)
        # a body in flight with parts on hinges: a free body for each part
        split = split_rigid(x0[group], u[group], 0.0025 * extent).to(dev)
        for part in range(1, int(split.max()) + 1):
            rows = group.clone()
            rows[group] = split == part
            body = refine(fit_free_body(model, rows, t1, path_t1), rows, backtest.start, t1, before_t1)
            result = {**entry, "gaussians": int(rows.sum()), "group": label}
            result["mse_learned"] = backtest.error(rows, None)
            result["mse_free_body"] = backtest.error(rows, body)
            result["free_body"] = result["mse_free_body"] < dyn.free_body_tolerance * result["mse_learned"]
            report.append(result)
            if result["free_body"]:
                chosen.append(rows)
    if not chosen:
        return none, report
    labels = none["labels"].clone()
    start, before_t_max = model.deform(t0), fit_views(t0, t_max)
    bodies = []
    for k, rows in enumerate(chosen):
        labels[rows] = k + 1
        body = refine(fit_free_body(model, rows, t0, path_t0), rows, start, t0, before_t_max)
        bodies.append(body.as_tensor())
    return {"t0": t0, "labels": labels, "bodies": torch.stack(bodies)}, report
