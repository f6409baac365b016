"""A chain of joints as one system (``extrapolation.joint_laws``): a part on a joint of its own in the
frame of a part on a joint (``joints.on_frame``: a double pendulum's second link on its first) has its
coordinate and its carrier's identified together, ``(q1, q2)'' = f(q1, q2, q1', q2')``
(``physics/identify.py``): each link's motion drives the other's, which one coordinate each, with the
other's path given, cannot predict.

The chain's model replaces the two links' own when it fits the whole path (identify's tests) and
predicts both links' Gaussians on the held-out frames better than the links' own models do (the
carrier's, or the learned physics where it has none, and the carried link's composed with it) and
within ``joint_law_tolerance`` of the learned physics. No images.

M: a link's Gaussians, T: frames, H: held-out frames.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..physics.free_body import split_rigid
from ..physics.identify import holdout_split, identify
from .joint_motion import joint_transforms, rms_distance, transformed_points


def pooled(errors: list[tuple[float, int]]) -> float:
    """The RMS over the Gaussians of several parts from each part's ``(rms, gaussians)``."""
    return math.sqrt(sum(e * e * n for e, n in errors) / max(sum(n for _, n in errors), 1))


def choose_chain(carrier: dict, link: dict, truth: torch.Tensor, times, learned, settings, own: float):
    """``(carrier part, link part) or None, report)``: the chain of the ``carrier`` (``joints`` frame
    entry: its joint ``part``, coordinate ``q`` [T] and ``rows``) and the ``link`` (``{"part"`` (its
    joint in the carrier's frame) ``, "q"`` [T] ``, "x0"`` [M, 3] (its means in that frame at the
    handover) ``, "rows"}``); ``truth`` [T, N, 3] every Gaussian's f_defo means over the frames;
    ``own``: the held-out RMS error of the two links' own predictions, pooled."""
    t = np.asarray(times, dtype=np.float64)
    q = np.stack([carrier["q"].numpy(), link["q"].numpy()], 1)
    angular = (carrier["part"]["joint"] == "hinge", link["part"]["joint"] == "hinge")
    model = identify(t, q, angular=angular, holdout_fraction=settings.joint_law_holdout)
    entry = {"chain": [carrier["report"], link["report"]], "adopted": False, **model.report()}
    if model.held_out_path is None or not np.isfinite(model.coefficients).all():
        return None, {**entry, "why": f"{model.why}: the links' own models"}
    n = holdout_split(len(t), settings.joint_law_holdout)
    held = torch.from_numpy(model.held_out_path)
    rotation, translation = joint_transforms(carrier["part"], held[:, 0])
    x_carrier = truth[-1][carrier["rows"].cpu()]
    carrier_means = transformed_points(x_carrier, rotation, translation)
    link_means = transformed_points(link["x0"], *joint_transforms(link["part"], held[:, 1]))
    link_means = link_means @ rotation.transpose(1, 2) + translation[:, None]
    rows = (carrier["rows"] | link["rows"]).cpu()
    learned_means = learned.means(float(t[n - 1]), [float(s) for s in t[n:]])
    chain = pooled(
        [
            (rms_distance(carrier_means, truth[n:, carrier["rows"].cpu()]), int(carrier["rows"].sum())),
            (rms_distance(link_means, truth[n:, link["rows"].cpu()]), int(link["rows"].sum())),
        ]
    )
    entry["position_rms"] = {
        "chain": chain,
        "own": own,
        "learned": rms_distance(learned_means[:, rows], truth[n:, rows]),
    }
    if model.active_kinds <= {"1"}:  # (a steady turn: the learned physics holds the carrier)
        why = "a constant acceleration, which the learned physics is: the links' own models"
    elif not model.adopted:
        why = f"{model.why}: the links' own models"
    elif model.growth_rate() * float(t[-1] - t[0]) > 1.0:
        why = "unstable (a small departure grows e-fold within the span): the links' own models"
    elif not chain < own:
        why = "the links' own models predict the held-out frames as well: theirs"
    elif not chain < settings.joint_law_tolerance * entry["position_rms"]["learned"]:
        why = "the learned physics predicts the held-out frames as well: the links' own models"
    else:
        stored = model.to_dict()
        pair = (
            {**carrier["part"], "model": stored, "coordinate": 0},
            {**link["part"], "model": stored, "coordinate": 1},
        )
        return pair, {**entry, "adopted": True, "why": "adopted"}
    return None, {**entry, "why": why}


def split_parts(x0, u, path, times, group, floor: float, snapshots: int = 4) -> torch.Tensor:
    """[M] labels 1, 2, ... of the rigid parts of the Gaussians ``group`` (``split_rigid``), split by
    f_trd's velocities ``u`` [N, 3] at their means ``x0`` at the handover or by f_defo's at one of
    ``snapshots`` earlier frames of their ``path`` (central differences at the ``times``), whichever
    gives the most parts (the handover's on a tie): two links of a chain can swing as one at the
    handover and apart earlier."""
    best = split_rigid(x0[group], u[group], floor)
    for k in np.linspace(1, len(path) - 2, snapshots).round().astype(int)[:-1]:
        velocity = (path[k + 1][group] - path[k - 1][group]) / float(times[k + 1] - times[k - 1])
        labels = split_rigid(path[k][group], velocity, floor)
        if int(labels.max()) > int(best.max()):
            best = labels
    return best
