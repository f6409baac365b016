"""Parts with identified models (``extrapolation.joint_laws``): a rigid part that turns on a hinge or
slides on a rail, whose coordinate ``q`` follows a model ``q'' = f(q, q')`` identified from f_defo's
path (``physics/identify.py``) that the learned physics, its accelerations held from the handover,
cannot follow (a pendulum swinging back, a spring, a wheel braking to rest); a chain of such parts; a
part on no joint.

For each rigid part of the moving Gaussians (``free_bodies.moving_groups``, split by
``chain.split_parts``; the free bodies' Gaussians left to them), f_defo's per-frame rigid transforms of
the part from the handover t0 back to t = 0 give a hinge (refitted to the positions) and a slider
(``physics/joint.py``); the one that reproduces f_defo's positions better, within
``joint_fit_tolerance`` of the part's radius of its best rigid motion per frame, gives ``q`` [T], and
``identify`` its model, chosen on the held-out end of ``q`` (``joint_law_holdout``). It is adopted when
it is more than a constant acceleration, is stable, beats moving on at the last velocity there, fits
the whole path, and predicts the part's positions there no worse than ``joint_law_tolerance`` times
the learned physics started at the same frame. A piece left on no model that an adopted part's
transforms carry along its path about as well as its own rigid motion does (``carried_by``: a
pendulum's rod, cut from its bob by f_trd's velocities) moves with that part. A piece that turns on a
joint of its own in the frame of a part with a model, adopted or not (``on_frame``: a box spinning on
a turntable), is put on that joint, its model chosen and backtested as above with the carrier's
carrying it, and the two coordinates identified together as one system (``chain.py``: a double
pendulum) where that predicts both better; a carrier whose model is not adopted moves only the part
it carries. A moving group none of whose pieces is on a joint gets the identified model of its
centre's coordinates (``unjointed.py``: a disc on springs, a puck after an impact), or where that is
not adopted, bounces on a floor if it did within the span (a thrown part, ``thrown.py``). Everything
else keeps the learned physics, and the report says why. No images.

N: Gaussians, M: a part's Gaussians, T: frames.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..physics.free_body import fit_rigid_transform
from ..physics.identify import holdout_split, identify
from ..physics.joint import (
    fit_hinge,
    fit_slider,
    refine_hinge,
)
from .chain import choose_chain, pooled, split_parts
from .free_bodies import moving_groups
from .joint_motion import joint_transforms, rms_distance, transformed_points
from .thrown import choose_thrown
from .unjointed import choose_unjointed

MIN_FRAMES = 8
"""Fewest frames of f_defo's path up to the handover that a joint law is identified from."""
MIN_GAUSSIANS = 20
"""Fewest Gaussians of a part (``rigid_components``' smallest group) put on a joint."""
ONE_BODY = 0.4
"""Largest RMS residual of a group's best rigid motion per frame, relative to its radius, for its
centre to be given a model (``unjointed.py``): a ball whose Gaussians slide over it as it turns
stays under it, Gaussians that f_defo loses or several bodies moving apart do not."""
RIGID_TOLERANCE = 0.2
"""Largest RMS residual of a part's best rigid motion per frame, relative to its radius, for it to be
put on a joint: a group whose pieces move apart (a box spinning on a turning table: 0.34) is cut into
its rigid parts, and a part whose Gaussians slide over it (a symmetric wheel: 0.56) keeps the learned
physics."""


def part_transforms(x0: torch.Tensor, path: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(R [T, 3, 3], T [T, 3])``: the rigid transforms that best carry a part's Gaussians from their
    means ``x0`` [M, 3] at the handover to each of their means ``path`` [T] x [M, 3] (Kabsch)."""
    fits = [fit_rigid_transform(x0, x) for x in path]
    return torch.stack([r for r, _ in fits]), torch.stack([t for _, t in fits])


def fit_joint(
    x0: torch.Tensor, path: list[torch.Tensor], min_turn: float = 0.0
) -> tuple[dict | None, torch.Tensor | None, dict]:
    """``(joint, q [T], residuals)`` of the part whose means are ``x0`` [M, 3] at the handover and
    ``path`` [T] x [M, 3] at the frames: the hinge or the slider (``fit_hinge`` about the part's mean,
    refitted to the positions by ``refine_hinge``; ``fit_slider``) whose transforms of ``q`` reproduce ``path`` with the smaller RMS residual, and
    ``residuals["rigid"]``, that of the best rigid transform of each frame. The
    residuals are relative to the part's radius (RMS distance from its mean at the handover); the
    joint is stored as plain tensors: ``{"joint": "hinge" | "slider", "axis"`` (the hinge's axis or
    the rail's direction) ``, "pivot"`` (zeros on a rail) ``, "base_rotation", "base_translation"}``.
    ``min_turn``: a hinge whose angle spans less over the path is no candidate (a straight motion is
    also a turn about a far axis)."""
    x = x0.detach().double().cpu()
    truth = torch.stack([p.detach().double().cpu() for p in path])
    radius = max(float((x - x.mean(0)).square().sum(-1).mean().sqrt()), 1e-12)
    rotation, translation = part_transforms(x, [p for p in truth])
    hinge, q_hinge = refine_hinge(x, truth, fit_hinge(rotation, translation, centre=x.mean(0))[0])
    slider, q_slider = fit_slider(rotation, translation)
    candidates = {
        "hinge": (
            {"joint": "hinge", "axis": hinge.axis, "pivot": hinge.pivot},
            hinge,
            q_hinge,
        ),
        "slider": (
            {"joint": "slider", "axis": slider.direction, "pivot": torch.zeros(3, dtype=torch.float64)},
            slider,
            q_slider,
        ),
    }
    residuals, best = {}, None
    for name, (joint, fitted, q) in candidates.items():
        if name == "hinge" and float(q.max() - q.min()) < min_turn:
            residuals[name] = math.inf
            continue
        joint = {**joint, "base_rotation": fitted.base_rotation, "base_translation": fitted.base_translation}
        residual = rms_distance(transformed_points(x, *joint_transforms(joint, q)), truth) / radius
        residuals[name] = residual if math.isfinite(residual) else math.inf
        if math.isfinite(residual) and (best is None or residual < residuals[best[0]["joint"]]):
            best = (joint, q)
    residuals["radius"] = radius
    residuals["rigid"] = rms_distance(transformed_points(x, rotation, translation), truth) / radius
    return (None, None, residuals) if best is None else (*best, residuals)


def frame_times(model, t0: float) -> list[float]:
    """The frame times up to ``t0`` (the handover, last), ``model.dt_max`` apart, t = 0 included."""
    steps = int(math.floor(t0 / model.dt_max + 1e-6))
    return [max(0.0, t0 - k * model.dt_max) for k in range(steps, -1, -1)]


def fits_joint(joint: dict, residuals: dict, settings) -> bool:
    """Whether a part moves rigidly (``RIGID_TOLERANCE``) and its ``joint`` reproduces its motion about
    as well as its best rigid motion per frame (``joint_fit_tolerance``)."""
    rigid = residuals["rigid"]
    return rigid <= RIGID_TOLERANCE and residuals[joint["joint"]] <= rigid + settings.joint_fit_tolerance


def _finite(value: float | None) -> float | None:
    """A number as ``summary.json`` can hold it (JSON has no NaN or infinity: null)."""
    return float(value) if value is not None and math.isfinite(value) else None


class _LearnedBacktest:
    """The learned physics started at f_defo's state at ``t1`` and run to the ``times`` after it (each
    Gaussian's mean; computed once for every part held out from the same frame)."""

    def __init__(self, predictor):
        self.predictor, self.runs = predictor, {}

    def means(self, t1: float, times: list[float]) -> torch.Tensor:
        """[T, N, 3] the learned physics' means at ``times`` from ``t1``."""
        key = (t1, tuple(times))
        if key not in self.runs:
            runs = [self.predictor.physics_from(t1, t)["means"] for t in times]
            self.runs[key] = torch.stack(runs).double().cpu()
        return self.runs[key]


def choose_part_law(
    x0: torch.Tensor,
    path: list[torch.Tensor],
    times: list[float],
    rows: torch.Tensor,
    learned: _LearnedBacktest,
    settings,
    fit: tuple | None = None,
    frame: tuple | None = None,
) -> tuple[dict | None, dict]:
    """``(stored part or None, report)`` of the part ``rows`` [N] bool, whose means are ``x0`` [M, 3]
    at the handover ``times[-1]`` and ``path`` [T] x [M, 3] at the increasing ``times`` [T] (module
    docstring). The stored part is its joint (``fit_joint``, or ``fit`` when already made) with
    ``law``, ``params`` [P] and the law's state ``q0``, ``v0`` at the handover. With ``frame``
    ``(R [H, 3, 3], T [H, 3], world [H, M, 3])``, ``x0`` and ``path`` are in a carrying part's frame
    and the held-out frames are scored in the world: the carrier's predicted transforms on them, and
    the part's means there; there a ``constant`` law may be adopted too, and no law need beat moving on
    at the last joint velocity (on a turning part, a steady turn or moving on is a path that the
    learned physics' accelerations, held, cannot keep bending: the learned physics is what it must
    beat). A report whose law was fitted also has ``"_frame"``: the part (adopted or
    not) with its coordinate ``q`` [T] over the frames and its predicted transforms on the held-out ones,
    for a part it may carry (``on_frame``)."""
    joint, q, residuals = fit if fit is not None else fit_joint(x0, path)
    entry: dict = {
        "gaussians": int(rows.sum()),
        "radius": residuals["radius"],
        "residual": {k: _finite(residuals[k]) for k in ("hinge", "slider", "rigid")},
        "joint": None if joint is None else joint["joint"],
        "adopted": False,
    }
    if joint is None or not fits_joint(joint, residuals, settings):
        return None, {**entry, "why": "not rigid, or on no hinge or rail: the learned physics"}
    t = np.asarray(times)
    # on a turning part a steady turn still bends, so there the model need not beat moving on at the
    # last joint velocity: the learned physics is what it must beat (below)
    model = identify(
        t,
        q.numpy(),
        angular=(joint["joint"] == "hinge",),
        holdout_fraction=settings.joint_law_holdout,
        **({} if frame is None else {"margin": math.inf}),
    )
    n = holdout_split(len(t), settings.joint_law_holdout)
    truth = torch.stack([p.detach().double().cpu() for p in path[n:]])
    entry.update(model.report())
    if model.held_out_path is None or not np.isfinite(model.coefficients).all():
        return None, {**entry, "why": f"{model.why}: the learned physics"}
    # the part's positions on the held-out frames: the model fitted to the frames before them, against
    # the learned physics started at the last of those frames
    held = joint_transforms(joint, torch.from_numpy(model.held_out_path[:, 0]))
    law_means = transformed_points(x0, *held)
    if frame is not None:  # a carried part: its frame's predicted motion, then its own, in the world
        law_means, truth = law_means @ frame[0].transpose(1, 2) + frame[1][:, None], frame[2]
    learned_means = learned.means(float(t[n - 1]), [float(s) for s in t[n:]])[:, rows.cpu()]
    entry["position_rms"] = {
        "law": rms_distance(law_means, truth),
        "learned": rms_distance(learned_means, truth),
    }
    part = {**joint, "model": model.to_dict(), "parent": None}
    entry["_frame"] = {"part": part, "q": q, "held": held}
    span = float(t[-1] - t[0])
    if model.active_kinds <= {"1"} and frame is None:  # (on a turning part, a constant turn still bends)
        why = "a constant acceleration, which the learned physics is: the learned physics"
    elif not model.adopted:
        why = f"{model.why}: the learned physics"
    elif model.growth_rate(q.numpy().mean()) * span > 1.0:
        why = "unstable (a small departure grows e-fold within the span): the learned physics"
    elif not entry["position_rms"]["law"] < settings.joint_law_tolerance * entry["position_rms"]["learned"]:
        why = "the learned physics predicts the held-out frames as well: the learned physics"
    else:
        return part, {**entry, "adopted": True, "why": "adopted"}
    return None, {**entry, "why": why}


@torch.no_grad()
def choose_joint_laws(predictor, extent: float) -> tuple[dict | None, list]:
    """The joint parts of a trained model (``extrapolation.joint_laws``): ``({"t0", "labels", "parts"},
    report)``, ``labels`` [N] long (0: not a joint part, k: ``parts[k - 1]``), ``parts`` one dict each
    (``choose_part_law``); ``(None, report)`` where none is adopted. ``report``: one entry per part."""
    model, state, settings = predictor.model, predictor.state, predictor.settings
    t0 = predictor.handover_time()
    times = frame_times(model, t0)
    if len(times) < MIN_FRAMES:
        return None, []
    (_, window), moved, u, groups = moving_groups(predictor, t0, extent, settings.free_body_window)
    x0 = window[0]
    bodies = state.free_bodies
    free = torch.zeros_like(moved)
    if bodies is not None and bodies["labels"].shape[0] == moved.shape[0] and abs(bodies["t0"] - t0) < 1e-9:
        free = bodies["labels"].to(moved.device) > 0
    path = [model.deform(float(t))["means"] for t in times]
    learned = _LearnedBacktest(predictor)
    labels = torch.zeros(moved.shape[0], dtype=torch.long, device=moved.device)
    parts, report, paths, left, frames, thrown = [], [], [], [], [], []
    for label in range(1, int(groups.max()) + 1):
        group = groups == label
        # a group on one joint is one part (its rigid split, from f_trd's velocities at the handover,
        # can cut one body in pieces, each with a noisier coordinate); else each rigid part of it
        whole = group & ~free
        fit = fit_joint(x0[whole], [p[whole] for p in path]) if int(whole.sum()) >= MIN_GAUSSIANS else None
        pieces = [(group, fit)]
        if fit is None or fit[0] is None or not fits_joint(fit[0], fit[2], settings):
            if int(whole.sum()) >= MIN_GAUSSIANS:
                thrown.append((label, whole))
            split = split_parts(x0, u, path, times, group, 0.0025 * extent).to(moved.device)
            pieces = [
                (group.clone().index_put_((group,), split == k), None) for k in range(1, int(split.max()) + 1)
            ]
        for rows, fit in pieces:
            entry = {"group": label, "free_body": int((rows & free).sum())}
            rows = rows & ~free  # a free body's Gaussians stay its own
            if int(rows.sum()) < MIN_GAUSSIANS:
                report.append({**entry, "gaussians": int(rows.sum()), "adopted": False, "why": "a free body"})
                continue
            x, part_path = x0[rows], [p[rows] for p in path]
            part, result = choose_part_law(x, part_path, times, rows, learned, settings, fit)
            frame = result.pop("_frame", None)  # (its law, adopted or not, as a frame for another part)
            report.append({**entry, **result})
            if frame is not None:
                frames.append({**frame, "report": len(report) - 1, "index": None, "rows": rows})
            if part is not None:
                parts.append(part)
                paths.append(frame["q"])
                labels[rows] = frames[-1]["index"] = len(parts)
            elif result.get("joint") is not None:
                left.append((rows, len(report) - 1))
    turning = []
    for rows, i in left:  # a piece of a part whose joint was adopted (a pendulum's rod, its bob) joins it
        known = {"radius": report[i]["radius"], "rigid": report[i]["residual"]["rigid"]}
        known = None if known["rigid"] is None else known  # (not finite: computed again)
        k = carried_by(x0[rows], [p[rows] for p in path], parts, paths, settings, known)
        if k is not None:
            labels[rows] = k + 1
            report[i].update(adopted=True, why=f"moves with joint part {k + 1}: its law", joins=k + 1)
        else:
            turning.append((rows, i))
    truth = torch.stack([p.detach().double().cpu() for p in path])
    for rows, i in turning:  # a part on a joint of its own on a turning part (a box on a turntable)
        found = on_frame([p[rows] for p in path], times, rows, learned, settings, frames, i)
        if found is None:
            continue
        part, result, frame, link = found
        carrier = report[frame["report"]]
        own = [(carrier["position_rms"]["law" if frame["index"] else "learned"], int(frame["rows"].sum()))]
        link = {**link, "rows": rows, "report": i}
        own.append((result["position_rms"]["law" if part is not None else "learned"], int(rows.sum())))
        pair, chained = choose_chain(frame, link, truth, times, learned, settings, pooled(own))
        report.append(chained)
        if part is None and pair is None:  # on a joint in its frame, but neither alone nor as a chain
            continue
        if pair is not None:  # one system: the carrier's Gaussians move by it too
            part = pair[1]
            if frame["index"] is None:
                parts.append(pair[0])
                frame["index"] = len(parts)
            parts[frame["index"] - 1] = pair[0]
            labels[frame["rows"]] = frame["index"]
        elif frame["index"] is None:  # the carrier's law moves the part, not the carrier's own Gaussians
            parts.append(frame["part"])
            frame["index"] = len(parts)
        parts.append({**part, "parent": frame["index"] - 1})
        labels[rows] = len(parts)
        carrier.setdefault("frame_of", []).append(len(parts))
        why = f"on a joint of its own on joint part {frame['index']}: their laws"
        report[i].update({**result, "adopted": True, "why": why, "on": frame["index"]})
    for label, rows in thrown:  # a group none of whose pieces is on a joint: its centre's model
        if bool((labels[rows] > 0).any()):
            continue
        entry = {"group": label, "free_body": int(((groups == label) & free).sum())}
        track = torch.stack([p[rows].detach().double().cpu() for p in path])
        x = x0[rows].detach().double().cpu()
        transforms = part_transforms(x, list(track))
        radius = max(float((x - x.mean(0)).square().sum(-1).mean().sqrt()), 1e-12)
        if rms_distance(transformed_points(x, *transforms), track) <= ONE_BODY * radius:
            part, result = choose_unjointed(*transforms, x, track, times, rows, learned, settings)
        else:
            part, result = None, {"gaussians": int(rows.sum()), "joint": "free", "adopted": False}
            result["why"] = "not one body (it moves rigidly about no centre): the learned physics"
        report.append({**entry, **result})
        if part is None:  # or one that bounces on a floor (f_defo rounds the bounce: no velocity jump)
            part, result = choose_thrown([p[rows] for p in path], times, rows, learned, settings)
            report.append({**entry, **result})
        if part is not None:
            parts.append(part)
            labels[rows] = len(parts)
    return ({"t0": t0, "labels": labels, "parts": parts} if parts else None), report


def carried_by(
    x0: torch.Tensor,
    path: list[torch.Tensor],
    parts: list[dict],
    paths: list,
    settings,
    residuals: dict | None = None,
) -> int | None:
    """The index of the joint part among ``parts`` (with their coordinates ``paths`` [T] over the frames)
    whose transforms carry the Gaussians ``x0`` [M, 3] along their ``path`` [T] x [M, 3] about as well
    as their own best rigid motion per frame (``joint_fit_tolerance`` of their radius, as ``fits_joint``):
    pieces of one rigid part that f_trd's velocities cut apart; None when no part does. ``residuals``:
    their ``fit_joint`` report's ``radius`` and ``rigid``, when already computed."""
    x = x0.detach().double().cpu()
    truth = torch.stack([p.detach().double().cpu() for p in path])
    if residuals is None:
        radius = max(float((x - x.mean(0)).square().sum(-1).mean().sqrt()), 1e-12)
        rigid = rms_distance(transformed_points(x, *part_transforms(x, list(truth))), truth) / radius
    else:
        radius, rigid = max(residuals["radius"], 1e-12), residuals["rigid"]
    best, best_residual = None, math.inf
    for k, (part, q) in enumerate(zip(parts, paths, strict=True)):
        residual = rms_distance(transformed_points(x, *joint_transforms(part, q)), truth) / radius
        if residual <= min(rigid + settings.joint_fit_tolerance, best_residual):
            best, best_residual = k, residual
    return best


def on_frame(
    path: list[torch.Tensor], times: list[float], rows, learned, settings, frames: list[dict], me: int
) -> tuple[dict | None, dict, dict, dict] | None:
    """``(part, report, frame, link)`` of the Gaussians ``rows``, on their ``path`` [T] x [M, 3] (the handover
    last), as a part on a joint of its own in the frame of one of the parts with a law (``frames``:
    ``choose_part_law``'s ``"_frame"`` with its ``"report"`` index; not the report ``me``): their path
    in that part's frame (its joint's transforms of its coordinate) put on a joint (``fit_joint``,
    ``fits_joint``) and its law chosen and backtested as ``choose_part_law`` does, the carrier's predicted
    motion and the part's composed on the held-out frames. The frame whose law predicts them best
    there, of those adopted, else of those whose law was fitted (its part None: the two may still be
    one system, ``chain.py``); ``link``: the part's joint, coordinate ``q`` [T] and means ``x0`` in that
    frame at the handover. None when none is."""
    truth = torch.stack([p.detach().double().cpu() for p in path])
    best = None
    for frame in frames:
        if frame["report"] == me:
            continue
        rotation, translation = joint_transforms(frame["part"], frame["q"])
        relative = (truth - translation[:, None]) @ rotation  # R^T (x - T), row vectors
        fit = fit_joint(relative[-1], list(relative))
        if fit[0] is None or not fits_joint(fit[0], fit[2], settings):
            continue
        held = frame["held"]
        seen = (*held, truth[-held[0].shape[0] :])
        part, result = choose_part_law(
            relative[-1], list(relative), times, rows, learned, settings, fit, seen
        )
        own = result.pop("_frame", None)
        if own is None:
            continue
        rank = (part is None, result["position_rms"]["law"])  # adopted first, then the better
        if best is None or rank < best[0]:
            best = (rank, (part, result, frame, {"part": own["part"], "q": own["q"], "x0": relative[-1]}))
    return None if best is None else best[1]
