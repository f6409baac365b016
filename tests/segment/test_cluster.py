"""Clustering recovers the parts of synthetic per-Gaussian parameters of known rigid motions, and the
choice of K without labels finds their count."""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from tracegs.segment.cluster import (
    choose_k,
    connected,
    partition_cost,
    refine,
    rigid_residual,
    segment,
    smooth,
    starts,
)
from tracegs.segment.config import SegmentConfig
from tracegs.segment.features import MotionFeatures, flow_groups, physics_groups


def _rotation(axis, angle):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


# part: (centre of its points, angular velocity w, pivot on the axis, linear velocity)
PARTS = [
    ((0.0, 0.0, -0.6), (0, 0, 0), (0, 0, 0), (0, 0, 0)),  # static base
    ((0.0, 0.0, 0.3), (0, 0, 2.0), (0, 0, 0), (0, 0, 0)),  # a blade turning about z through the origin
    ((0.6, 0.0, 0.0), (0, -1.2, 0), (0.45, 0, 0), (0, 0, 0)),  # a lid on a hinge
    ((-0.6, 0.3, 0.0), (0, 0, 0), (0, 0, 0), (0.4, 0.1, 0)),  # a carriage that slides
    ((-0.3, -0.6, 0.2), (1.5, 0, 0), (-0.3, -0.6, 0.2), (0.2, 0, 0)),  # a wheel rolling along
]


def synthetic_parts(
    noise: float = 0.03, n: int = 300, t_max: float = 0.75, times: int = 8, seed: int = 0, parts=PARTS
):
    """MotionFeatures of Gaussians on the ``parts`` (default: the ones above), with f_trd-like parameters (v_bar = v - w x pivot,
    w) and noise, and the exact trajectories; returns (features, true part of each Gaussian)."""
    rng = np.random.default_rng(seed)
    x_end, truth, v_bar, omega, traj, velocity = [], [], [], [], [], []
    ts = np.linspace(0, t_max, times)
    for p, (centre, w, pivot, v) in enumerate(parts):
        rest = np.asarray(centre) + 0.12 * rng.standard_normal((n, 3))
        w, pivot, v = map(np.asarray, (w, pivot, v))
        speed = np.linalg.norm(w)
        path = []
        for t in ts:
            r = _rotation(w, speed * t) if speed > 0 else np.eye(3)
            path.append((rest - pivot) @ r.T + pivot + v * t)
        path = np.stack(path)  # [S, n, 3]
        traj.append(path)
        x_end.append(path[-1])
        truth.append(np.full(n, p))
        vb = v - np.cross(w, pivot + v * t_max)  # the particle velocity is v_bar + w x x
        v_bar.append(vb + noise * rng.standard_normal((n, 3)) * max(np.linalg.norm(vb), 0.3))
        omega.append(w + noise * rng.standard_normal((n, 3)) * max(speed, 0.3))
        velocity.append(vb + np.cross(w, path[-1]))
    traj = np.concatenate(traj, axis=1)
    truth = np.concatenate(truth)
    static = truth == 0
    settings = SegmentConfig()
    groups, weights = physics_groups(
        torch.tensor(np.concatenate(v_bar)),
        torch.tensor(np.concatenate(omega)),
        torch.tensor(static),
        settings,
    )
    velocity = np.concatenate(velocity)
    velocity = (
        velocity + noise * rng.standard_normal(velocity.shape) * np.linalg.norm(velocity, axis=1)[:, None]
    )
    features = MotionFeatures(
        {k: g.numpy() for k, g in groups.items()}, weights, traj[-1], static, traj, velocity,
        np.ones(len(truth)), t_max, 0.003,
    )  # fmt: skip
    return features, truth


def agreement(labels: np.ndarray, truth: np.ndarray) -> float:
    """Share of the Gaussians in the segment matched one-to-one to their part (Hungarian)."""
    from scipy.optimize import linear_sum_assignment

    counts = np.zeros((labels.max() + 1, truth.max() + 1))
    np.add.at(counts, (labels, truth), 1)
    rows, cols = linear_sum_assignment(counts, maximize=True)
    return counts[rows, cols].sum() / len(labels)


def test_kmeans_on_the_physics_recovers_known_rigid_parts():
    features, truth = synthetic_parts()
    seg = segment(features, SegmentConfig(), k=len(PARTS))
    assert seg.k == len(PARTS) and seg.has_static
    assert agreement(seg.labels, truth) > 0.99
    assert (seg.labels[truth == 0] == 0).all()  # the static group is label 0


def test_auto_k_finds_the_number_of_parts():
    features, truth = synthetic_parts()
    k, table = choose_k(features, SegmentConfig())
    assert k == len(PARTS)
    tried = [row["k"] for row in table]
    assert tried[0] == 2 and len(PARTS) in tried
    residual = {row["k"]: row["rigid_residual"] for row in table}
    # one part short is not rigid: the next K cuts its residual by more than the rule's gain
    assert SegmentConfig().rigid_gain * residual[len(PARTS) - 1] > 1.5 * residual[len(PARTS)]
    seg = segment(features, SegmentConfig(), k=None)
    assert seg.k == len(PARTS) and agreement(seg.labels, truth) > 0.99


def test_flow_features_split_a_turning_part():
    """The paper's point: scene flow differs across one turning part (tip against hub), so K-means on it
    splits the blade, where the physics features (equal over a rigid part) keep it whole."""
    features, truth = synthetic_parts()
    groups, weights = flow_groups(torch.tensor(features.trajectories))
    flow = dataclasses.replace(features, groups={k: v.numpy() for k, v in groups.items()}, weights=weights)
    raw = SegmentConfig(smooth_neighbours=0, refine_iterations=0)  # K-means alone
    assert agreement(segment(flow, raw, k=len(PARTS)).labels, truth) < 0.97
    assert agreement(segment(features, raw, k=len(PARTS)).labels, truth) > 0.99


def test_rigid_residual_is_zero_for_rigid_parts_and_not_for_merged_ones():
    features, truth = synthetic_parts(noise=0.0)
    x, u = features.positions, features.velocities
    assert rigid_residual(x, u, truth) < 1e-9
    assert rigid_residual(x, u, np.minimum(truth, 1)) > 0.1
    assert rigid_residual(x, np.zeros_like(u), truth) == 0.0


def test_a_stray_patch_joins_what_surrounds_it():
    """A few Gaussians of the base that K-means put with the blades (their motion alike) take the
    label around them; the static group, in many pieces, is left whole."""
    rng = np.random.default_rng(2)
    base = rng.random((400, 3)) * [1, 1, 0.1]
    blades = rng.random((400, 3)) * [1, 1, 0.1] + [0, 0, 2]
    far = rng.random((100, 3)) * 0.2 + [5, 5, 5]  # a still object apart from the base
    points = np.concatenate([base, blades, far])
    labels = np.repeat([0, 1, 0], [400, 400, 100])
    patch = np.flatnonzero(np.linalg.norm(points - [0.5, 0.5, 0.05], axis=1) < 0.12)
    stray = labels.copy()
    stray[patch] = 1
    assert 3 <= len(patch) < 100
    assert (connected(stray, points, 8, 0.25, keep=0) == labels).all()
    assert (connected(labels, points, 8, 0.25, keep=0) == labels).all()
    assert (connected(stray, points, 8, 0.0, keep=0) == stray).all()


def test_smoothing_relabels_isolated_points_only():
    rng = np.random.default_rng(1)
    points = np.concatenate([rng.random((200, 3)), rng.random((200, 3)) + [3, 0, 0]])
    labels = np.repeat([0, 1], 200)
    noisy = labels.copy()
    noisy[[5, 250]] = [1, 0]
    assert (smooth(noisy, points, 8) == labels).all()
    assert (smooth(labels, points, 0) == labels).all()


def test_k_one_is_one_segment_and_bad_k_is_refused():
    features, _ = synthetic_parts()
    seg = segment(features, SegmentConfig(), k=1)
    assert seg.k == 1 and not seg.has_static and (seg.labels == 0).all()
    with pytest.raises(ValueError, match="at least 1"):
        segment(features, SegmentConfig(), k=0)


def hinged_wing(n: int = 1500, t_max: float = 0.75, times: int = 8, seed: int = 3):
    """MotionFeatures of a body sliding along x and a wing beside it turning about a hinge on the body's
    edge (the y axis through x = z = 0 at t = 0), exact trajectories and velocities; and the truth (0
    body, 1 wing)."""
    rng = np.random.default_rng(seed)
    body = rng.random((n, 3)) * [0.5, 0.4, 0.05] - [0.5, 0.2, 0.025]
    wing = rng.random((n, 3)) * [0.5, 0.4, 0.05] - [0.0, 0.2, 0.025]
    v, w = np.array([0.3, 0.0, 0.0]), np.array([0.0, 1.5, 0.0])
    ts = np.linspace(0, t_max, times)
    rot = [_rotation(w, np.linalg.norm(w) * t) for t in ts]
    traj = np.stack(
        [np.concatenate([body + v * t, wing @ r.T + v * t]) for t, r in zip(ts, rot, strict=True)]
    )
    x = traj[-1]
    velocity = np.concatenate([np.tile(v, (n, 1)), v + np.cross(w, x[n:] - v * t_max)])
    truth = np.repeat([0, 1], n)
    static = np.zeros(2 * n, dtype=bool)
    features = MotionFeatures({}, {}, x, static, traj, velocity, np.ones(2 * n), t_max, 0.003)
    return features, truth, np.concatenate([body, wing])


def test_refinement_gives_a_hinge_band_back_to_the_part_whose_motion_it_follows():
    """K-means on one instant's features can put the strip of a wing by its hinge with the body (the
    motions differ little there); each Gaussian's fit to the segments' rigid motions over the span,
    averaged over its neighbours, gives the strip back, and labels that are right stay as they are."""
    features, truth, rest = hinged_wing()
    band = (truth == 1) & (rest[:, 0] > 0.04) & (rest[:, 0] < 0.15)
    wrong = np.where(band, 0, truth)
    settings = SegmentConfig()
    fixed = refine(wrong, features, settings, has_static=False)
    assert band.sum() > 200
    assert (fixed[band] == 1).mean() > 0.95
    assert (fixed == truth).mean() > 0.99
    kept = refine(truth, features, settings, has_static=False)
    assert (np.abs(rest[kept != truth, 0]) < 0.03).all()  # only on the hinge, where the motions meet
    same = refine(wrong, features, dataclasses.replace(settings, refine_iterations=0), has_static=False)
    assert (same == wrong).all()


def hinged_pair(n: int = 800, t_max: float = 0.75, times: int = 8, seed: int = 0):
    """MotionFeatures of a seat and a backrest turning about one hinge (the -y axis through the origin)
    at 0.76 and 0.91 rad/s, exact trajectories and velocities, whose feature groups other than the spin
    carry a decoy: a split across both parts by the side of y they lie on; and the truth (0 seat, 1
    backrest)."""
    rng = np.random.default_rng(seed)
    seat = rng.random((n, 3)) * [0.5, 0.6, 0.03] - [0.5, 0.3, 0.015]
    back = rng.random((n, 3)) * [0.03, 0.6, 0.5] - [0.015, 0.3, -0.02]
    truth = np.repeat([0, 1], n)
    spin = np.where(truth == 0, 0.76, 0.91)
    turn = [
        np.stack([_rotation((0, -1, 0), w * t) for w in (0.76, 0.91)])[truth]
        for t in np.linspace(0, t_max, times)
    ]
    traj = np.stack([np.einsum("nij,nj->ni", r, np.concatenate([seat, back])) for r in turn])
    omega = np.zeros((2 * n, 3))
    omega[:, 1] = -spin
    side = (traj[-1][:, 1:2] > 0).astype(float)
    jitter = lambda c: 0.01 * rng.standard_normal((2 * n, c))  # noqa: E731
    groups = {"speed": side + jitter(1), "velocity": side * [1, 0, 0] + jitter(3),
              "spin": spin[:, None] + jitter(1), "axis": side * [0, 0, 1] + jitter(3)}  # fmt: skip
    velocity = np.cross(omega, traj[-1])
    static = np.zeros(2 * n, dtype=bool)
    features = MotionFeatures(groups, dict.fromkeys(groups, 1.0), traj[-1], static, traj, velocity,
                              np.ones(2 * n), t_max, 0.003)  # fmt: skip
    return features, truth


def test_the_refinement_starts_from_each_feature_group_and_keeps_the_most_rigid_partition():
    """K-means on the weighted features follows a decoy most groups share and cuts across the seat and
    the backrest; the refinement, a local descent, does not get back in one round. Started also from
    each group alone, the partition of lowest rigid cost is the parts (the spin alone splits them)."""
    features, truth = hinged_pair()
    decoy = (features.positions[:, 1] > 0).astype(np.int64)
    assert partition_cost(truth, features, False) < 1e-6 < partition_cost(decoy, features, False)
    one_round = SegmentConfig(refine_iterations=1)
    weighted = segment(features, dataclasses.replace(one_round, starts="features"), k=2).labels
    assert agreement(weighted, truth) < 0.8
    seg = segment(features, one_round, k=2).labels
    assert agreement(seg, truth) > 0.99


def test_a_constant_feature_group_is_no_start_and_a_start_short_of_segments_loses():
    """A group the same on every moving Gaussian (w/|w| of parts that only translate, say) gives
    K-means nothing to split: it is not a start. And a start whose partition kept fewer segments than
    asked never wins on its (lower) rigid cost."""
    features, truth = hinged_pair()
    features.groups["axis"] = np.zeros_like(features.groups["axis"])
    assert "axis" not in starts(features, SegmentConfig())
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # K-means would warn of fewer distinct clusters than asked
        seg = segment(features, SegmentConfig(), k=2)
    assert seg.k == 2 and agreement(seg.labels, truth) > 0.99
    one = np.zeros_like(truth)
    assert partition_cost(one, features, False) > partition_cost(truth, features, False)


def test_raw_units_cluster_too():
    """``--settings.normalise none`` weighs the groups in their own units, and still recovers the parts
    of the synthetic scene (their motions differ in every unit)."""
    features, truth = synthetic_parts()
    seg = segment(features, SegmentConfig(normalise="none"), k=len(PARTS))
    assert seg.k == len(PARTS) and agreement(seg.labels, truth) > 0.95
