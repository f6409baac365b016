"""Grouping Gaussians by their motion: K-means (scikit-learn) on the normalised, weighted feature
groups, the static group apart, neighbour smoothing of the labels (scipy's cKDTree), and the choice
of K without labels from rigid fits.

Labels: 0 .. K-1, the static group first (when there is one), then the moving segments by size.
N: Gaussians, S: times, F: feature columns.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..physics.free_body import fit_rigid_transform
from .config import SegmentConfig
from .features import MotionFeatures, twist_design


@dataclass
class Segmentation:
    """Labels of every Gaussian and how K was chosen."""

    labels: np.ndarray
    """[N] int64 in 0 .. k - 1."""
    k: int
    has_static: bool
    """Whether label 0 is the static group."""
    auto_k: list[dict] = field(default_factory=list)
    """With ``--auto-k``: one entry per K tried, ``{"k", "rigid_residual"}`` (``rigid_residual``)."""


def feature_matrix(
    features: MotionFeatures, rows: np.ndarray, normalise: str, only: str | None = None
) -> np.ndarray:
    """[M, F] the weighted feature groups of the Gaussians ``rows`` (``only``: that one group alone);
    with ``normalise="group"`` each group is first scaled to unit RMS (about its mean) over these
    Gaussians, so a weight is a share of the distance whatever the group's units."""
    columns = []
    for name, group in features.groups.items():
        if only is not None and name != only:
            continue
        g = group[rows]
        if normalise == "group":
            spread = np.sqrt(((g - g.mean(0)) ** 2).sum(1).mean())
            g = g / max(spread, 1e-12)
        columns.append((1.0 if only else features.weights[name]) * g)
    return np.concatenate(columns, axis=1)


def kmeans(matrix: np.ndarray, k: int, seed: int) -> np.ndarray:
    """[M] cluster of each row, K-means with 10 restarts (k >= number of rows: one row each)."""
    from sklearn.cluster import KMeans

    if k <= 1 or len(matrix) == 0:
        return np.zeros(len(matrix), dtype=np.int64)
    if k >= len(matrix):
        return np.arange(len(matrix), dtype=np.int64)
    return KMeans(n_clusters=k, n_init=10, random_state=seed).fit_predict(matrix).astype(np.int64)


def smooth(labels: np.ndarray, positions: np.ndarray, neighbours: int, passes: int = 2) -> np.ndarray:
    """Each label replaced by the most common label among the point and its ``neighbours`` nearest
    points (``passes`` times): isolated mislabelled Gaussians join the part around them."""
    from scipy.spatial import cKDTree

    if neighbours <= 0 or len(labels) <= neighbours:
        return labels
    _, nn = cKDTree(positions).query(positions, neighbours + 1)
    k = int(labels.max()) + 1
    for _ in range(passes):
        votes = np.zeros((len(labels), k))
        np.add.at(votes, (np.repeat(np.arange(len(labels)), nn.shape[1]), labels[nn].ravel()), 1.0)
        votes[np.arange(len(labels)), labels] += 0.5  # ties keep the label
        labels = votes.argmax(1)
    return labels


def rigid_residual(
    positions: np.ndarray, velocities: np.ndarray, labels: np.ndarray, weights: np.ndarray | None = None
) -> float:
    """How far the Gaussians' velocities are from one rigid motion per segment: for each segment the
    twist (V, W) that best explains its velocities (u ~ V + W x (x - c), weighted least squares about
    the weighted centre c), and the weighted mean length of the residuals over every Gaussian, divided
    by the weighted mean speed (0: every segment moves rigidly; 1: as far off as the motion itself).
    Means of lengths, not RMS: the few Gaussians K-means puts in a neighbouring part would dominate
    an RMS.
    positions, velocities [N, 3], labels [N], weights [N] (default 1)."""
    w = np.ones(len(labels)) if weights is None else np.asarray(weights, dtype=np.float64)
    speed = float((w * np.linalg.norm(velocities, axis=1)).sum())
    if speed <= 0:
        return 0.0
    total = 0.0
    for label in np.unique(labels):
        rows = labels == label
        x, u, wr = positions[rows], velocities[rows], w[rows]
        total += float((wr * np.linalg.norm(fit_twist(x, u, wr)(x) - u, axis=1)).sum())
    return total / speed


def fit_twist(x: np.ndarray, u: np.ndarray, w: np.ndarray):
    """The rigid motion (V, W) about the ``w``-weighted centre c of ``x`` [M, 3] that best explains the
    velocities ``u`` [M, 3] (``u ~ V + W x (x - c)``, weighted least squares), as a function giving its
    velocity at any points [N, 3]."""
    c = (x * w[:, None]).sum(0) / max(w.sum(), 1e-12)
    a = twist_design(torch.as_tensor(x - c)).numpy()
    sw = np.sqrt(w)[:, None, None]
    sol, *_ = np.linalg.lstsq((a * sw).reshape(-1, 6), (u * sw[..., 0]).reshape(-1), rcond=None)
    return lambda points: twist_design(torch.as_tensor(points - c)).numpy() @ sol


def connected(
    labels: np.ndarray, positions: np.ndarray, neighbours: int, min_share: float, keep: int | None = None
) -> np.ndarray:
    """A part is one piece: each moving segment's pieces (connected components of the graph joining every
    Gaussian to its ``neighbours`` nearest of the same label) smaller than ``min_share`` of the segment
    take the label most common among their other neighbours. K-means on motion alone can join a patch
    of another part whose few, weakly seen Gaussians f_defo moved alike (a patch of a base disc turning
    with the blades above it). The segment ``keep`` (the static group: every still object of the
    scene, in as many pieces) is left as it is."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    if neighbours <= 0 or len(labels) <= neighbours:
        return labels
    _, nn = cKDTree(positions).query(positions, neighbours + 1)
    i, j = np.repeat(np.arange(len(labels)), neighbours), nn[:, 1:].ravel()
    same = labels[i] == labels[j]
    graph = coo_matrix((np.ones(int(same.sum())), (i[same], j[same])), shape=(len(labels),) * 2)
    _, piece = connected_components(graph, directed=False)
    sizes = np.bincount(piece)
    segment_size = np.bincount(labels)
    out = labels.copy()
    small = sizes[piece] < min_share * segment_size[labels]
    if keep is not None:
        small &= labels != keep
    for p in np.unique(piece[small]):
        rows = np.flatnonzero(piece == p)
        around = labels[nn[rows, 1:]].ravel()
        around = around[around != labels[rows[0]]]
        if len(around):
            out[rows] = np.bincount(around).argmax()
    return out


def segment(features: MotionFeatures, settings: SegmentConfig, k: int | None = None) -> Segmentation:
    """Labels of every Gaussian: the static group, and K-means on the features of the others into
    ``k`` segments in all (the static group counted), or with ``k=None`` the K of :func:`choose_k`."""
    if k is None:
        k, table, labels = choose_k(features, settings, with_labels=True)
        return _result(labels, table)
    if k < 1:
        raise ValueError(f"K must be at least 1, got {k}")
    return _result(_partition(features, settings, k), [])


def choose_k(features: MotionFeatures, settings: SegmentConfig, with_labels: bool = False) -> tuple:
    """K without labels, from how rigidly the segments move (``rigid_residual`` of the moving
    Gaussians' velocities, weighted by opacity, after the smoothing and the one-piece rule): trying
    K = 1 .. ``settings.k_max`` (the static group counted), the smallest K whose residual is under
    ``settings.rigid_tolerance``, else the smallest K that no larger K (up to ``k_max``) cuts to
    ``settings.rigid_gain`` of its residual. A merge of two parts with different motions leaves a residual of
    the order of their relative speed; a part split in two gains little. Every K tried, with its
    residual, is returned. (A rigid residual measures what a motion segment is, one rigid motion;
    silhouette or BIC scores measure how compact clusters are in feature space, which the feature
    weights change.) ``with_labels``: also the labels of the K chosen (``_partition``'s)."""
    has_static = bool(features.static.any())
    moving = int((~features.static).sum())
    table: list[dict] = []
    partitions = {}
    first = 1 + int(has_static)
    for k in range(first, max(settings.k_max, first) + 1):
        labels = partitions[k] = _partition(features, settings, k)
        rows = labels != -1  # the moving segments
        residual = rigid_residual(
            features.positions[rows], features.velocities[rows], labels[rows], features.opacity[rows]
        )
        table.append({"k": k, "rigid_residual": residual})
        if residual <= settings.rigid_tolerance or moving <= k:
            break
    chosen = table[-1]["k"]
    if table[-1]["rigid_residual"] > settings.rigid_tolerance:
        for i, row in enumerate(table):  # the first K that no larger K improves on by the gain
            later = table[i + 1 :]
            if all(other["rigid_residual"] > settings.rigid_gain * row["rigid_residual"] for other in later):
                chosen = row["k"]
                break
    return (chosen, table, partitions[chosen]) if with_labels else (chosen, table)


def _partition(features: MotionFeatures, settings: SegmentConfig, k: int) -> np.ndarray:
    """[N] labels of ``k`` segments: the static group (-1 here, when there is one and k > 1), K-means
    on the features of the others, the smoothing and the one-piece rule, the refinement; from each of
    ``starts`` K-means partitions, the refined one whose segments' rigid motions explain the Gaussians
    best (``partition_cost``)."""
    static = features.static
    has_static = bool(static.any()) and k > 1  # K = 1: one segment, the static Gaussians included
    best, best_key = None, None
    candidates = starts(features, settings)
    for only in candidates:
        labels = _labels(features, settings, np.flatnonzero(~static), k - int(has_static), only)
        if has_static:
            labels = np.where(static, -1, labels)
        labels = _tidy(_ordered(labels), features, settings, has_static)
        if settings.refine_iterations > 0:
            labels = refine(labels, features, settings, has_static)
            labels = _tidy(labels, features, settings, has_static)
        # a start that kept fewer segments than asked loses to one that kept them, whatever its cost
        cost = partition_cost(labels, features, has_static) if len(candidates) > 1 else 0.0
        key = (-len(np.unique(labels)), cost)
        if best_key is None or key < best_key:
            best, best_key = labels, key
    return np.where(best == 0, -1, best) if has_static else best


def starts(features: MotionFeatures, settings: SegmentConfig) -> list[str | None]:
    """The K-means partitions the refinement starts from: the weighted features (None) and, with
    ``settings.starts == "groups"`` and the refinement on, each feature group alone. K-means in one
    space can settle where two parts' motions differ in one group only (a seat and a backrest turning
    about one hinge at 0.76 and 0.91 rad/s) and the refinement, a local descent, keeps that split; its
    rigid cost over the span tells the partitions apart without labels."""
    if settings.starts != "groups" or settings.refine_iterations <= 0 or len(features.groups) < 2:
        return [None]
    moving = ~features.static
    return [None] + [
        name
        for name, group in features.groups.items()
        if name != "position" and moving.any() and np.ptp(group[moving], axis=0).max() > 0  # not constant
    ]


def partition_cost(labels: np.ndarray, features: MotionFeatures, has_static: bool) -> float:
    """How badly the segments' rigid motions explain the moving Gaussians of ``labels`` (0 .. K-1, 0 the
    static group when ``has_static``): each Gaussian's ``rigid_costs`` for its own segment, trajectory
    and velocity each over its mean over the moving Gaussians, averaged weighted by opacity."""
    scales = _scales(features)
    moving = ~features.static
    if scales is None or not moving.any():
        return 0.0
    w = features.opacity
    cost_x, cost_u = rigid_costs(labels, int(labels.max()) + 1, features.trajectories, features.velocities, features.positions,
                                 w, static_first=has_static)  # fmt: skip
    own = np.arange(len(labels)), labels
    cost = cost_x[own] / scales[0] + cost_u[own] / scales[1]
    return float((w * cost)[moving].sum() / max(w[moving].sum(), 1e-12))


def _scales(features: MotionFeatures) -> tuple[float, float] | None:
    """(mean displacement over the span, mean speed) of the moving Gaussians, opacity-weighted: the units
    of the refinement's two costs (None when nothing moves)."""
    traj, u, w = features.trajectories, features.velocities, features.opacity
    moving = ~features.static
    disp = np.linalg.norm(traj - traj[:1], axis=2).mean(0)
    total = max(w[moving].sum(), 1e-12)
    scale_x = float((w * disp)[moving].sum() / total)
    scale_u = float((w * np.linalg.norm(u, axis=1))[moving].sum() / total)
    return (scale_x, scale_u) if scale_x > 0 and scale_u > 0 else None


def refine(
    labels: np.ndarray, features: MotionFeatures, settings: SegmentConfig, has_static: bool
) -> np.ndarray:
    """Labels 0 .. K-1 (0 the static group when ``has_static``) after ``settings.refine_iterations``
    rounds of: fit each segment's rigid motion, then give each Gaussian the segment whose motion best
    explains its own, the costs averaged (opacity-weighted) over its ``settings.smooth_neighbours``
    nearest neighbours; a Gaussian that moved more than the static threshold stays out of the static
    group (one that moved less may belong to a moving part: by its hinge, or one that starts from rest).
    A Gaussian's cost for a segment is how far the segment's rigid transforms move
    it from its f_defo trajectory (``rigid_costs``) plus how far the segment's twist is from its
    velocity, each over its mean over the moving Gaussians. K-means on features of one instant splits
    parts where the features blend (a wing by the body it is hinged to); the trajectories over the
    whole span and the neighbours' vote draw the line where the motions part."""
    from scipy.spatial import cKDTree

    traj, u, w = features.trajectories, features.velocities, features.opacity
    moving = ~features.static
    scales = _scales(features)
    k = int(labels.max()) + 1
    if k < 2 or scales is None:
        return labels
    scale_x, scale_u = scales
    nb = min(settings.smooth_neighbours + 1, len(labels))
    _, nn = cKDTree(features.positions).query(features.positions, nb)
    nn = nn.reshape(len(labels), nb)
    wn = w[nn] + 1e-9
    for _ in range(settings.refine_iterations):
        cost = rigid_costs(labels, k, traj, u, features.positions, w, static_first=has_static)
        cost = cost[0] / scale_x + cost[1] / scale_u
        cost = (cost[nn] * wn[..., None]).sum(1) / wn.sum(1)[:, None]
        if has_static:  # what moved more than the static threshold is not static
            cost[moving, 0] = np.inf
        new = cost.argmin(1)
        if np.array_equal(new, labels) or len(np.unique(new)) < len(np.unique(labels)):
            break  # settled, or a segment would vanish: K stays what was asked
        labels = new
    return labels


def rigid_costs(
    labels: np.ndarray,
    k: int,
    traj: np.ndarray,
    u: np.ndarray,
    x: np.ndarray,
    w: np.ndarray,
    static_first: bool,
) -> tuple[np.ndarray, np.ndarray]:
    """([N, K], [N, K]) for every Gaussian and segment: the mean distance over the sampled times from
    its trajectory ``traj`` [S, N, 3] to where the segment's rigid transforms (weighted Kabsch fits of the
    segment's trajectories from the first time to each) carry its first position, and the distance
    from its velocity ``u`` [N, 3] at ``x`` [N, 3] to the segment's twist there. With ``static_first``
    segment 0 is the static group: the identity and no velocity. A segment of fewer than 3 Gaussians
    costs infinity."""
    n, s = len(labels), len(traj)
    cost_x, cost_u = np.full((n, k), np.inf), np.full((n, k), np.inf)
    for j in range(k):
        rows = labels == j
        if static_first and j == 0:
            cost_x[:, j] = np.linalg.norm(traj - traj[:1], axis=2).mean(0)  # the identity's
            cost_u[:, j] = np.linalg.norm(u, axis=1)
            continue
        if rows.sum() < 3:
            continue
        total = np.zeros(n)
        for t in range(1, s):
            r, shift = fit_rigid_transform(
                *(torch.as_tensor(v) for v in (traj[0][rows], traj[t][rows], w[rows]))
            )
            total += np.linalg.norm(traj[0] @ r.numpy().T + shift.numpy() - traj[t], axis=1)
        cost_x[:, j] = total / max(s - 1, 1)
        cost_u[:, j] = np.linalg.norm(fit_twist(x[rows], u[rows], w[rows])(x) - u, axis=1)
    return cost_x, cost_u


def _result(labels: np.ndarray, table: list[dict]) -> Segmentation:
    """The segmentation of :func:`_partition`'s labels: renumbered, the static group first."""
    has_static = bool((labels == -1).any())
    labels = _ordered(labels)
    return Segmentation(labels, int(labels.max()) + 1, has_static, table)


def _tidy(
    labels: np.ndarray, features: MotionFeatures, settings: SegmentConfig, has_static: bool
) -> np.ndarray:
    """Smoothing, then the one-piece rule, on labels 0 .. K-1 (0 the static group when ``has_static``)."""
    labels = smooth(labels, features.positions, settings.smooth_neighbours)
    keep = 0 if has_static else None
    return connected(labels, features.positions, settings.smooth_neighbours, settings.piece_share, keep)


def _labels(
    features: MotionFeatures, settings: SegmentConfig, moving: np.ndarray, k: int, only: str | None = None
) -> np.ndarray:
    """[N] K-means label of the moving Gaussians into ``k`` clusters (0 elsewhere), on the weighted
    features or on the group ``only``."""
    labels = np.zeros(len(features.static), dtype=np.int64)
    if len(moving) and k >= 1:
        matrix = feature_matrix(features, moving, settings.normalise, only)
        labels[moving] = kmeans(matrix, k, settings.seed)
    return labels


def _ordered(labels: np.ndarray) -> np.ndarray:
    """Labels renumbered 0 .. K-1: -1 (the static group) first, then the others by decreasing size."""
    ids, counts = np.unique(labels, return_counts=True)
    order = sorted(range(len(ids)), key=lambda i: (ids[i] != -1, -counts[i], ids[i]))
    new = np.empty(len(ids), dtype=np.int64)
    new[order] = np.arange(len(ids))
    return new[np.searchsorted(ids, labels)]
