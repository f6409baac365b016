"""Free rigid bodies: the future of a part that moves as one body under a constant acceleration.

A spinning body that falls is what TRACE's per-particle physics cannot hold: its equivalent
acceleration ``a_bar = a_c - w x v_c(t)`` changes in time, and what f_trd learns of it at the end of
the training span is off (docs/PHYSICS.md, "A free body per part"). A free body holds it exactly:
a pivot on a parabola ``c0 + v s + a s^2 / 2`` (gravity) and a constant spin ``w`` about it. It is
the wrong model for a part on a hinge, which the learned physics holds by construction, so it is
chosen per part after training (``extrapolate/free_bodies.py``, ``choose_free_bodies``): a part that touches
nothing still (``isolation``) and whose free body does not predict the last training images clearly
worse than the learned physics. The parts are found without labels (``rigid_components``).

Pure functions on tensors; the model applies the chosen bodies in ``TraceModel.state_at``.
Not in the paper (``extrapolation.free_bodies``; off in ``paper``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from .so3 import quat_multiply, quat_normalize, rodrigues, rotmat_to_quat, skew

FREE_BODY_NUMBERS = 15
"""A free body's numbers as stored (``FreeBody.as_tensor``)."""


@dataclass
class FreeBody:
    """A rigid body's motion from its state at time ``t0``: pivot ``c0`` (a point of the body as it is
    at ``t0``) moving at ``v + a s`` (``s = t - t0``) from ``c0 + shift`` and turning about it at the
    constant angular velocity ``w`` (world frame, float64). ``shift`` moves the whole body at ``t0``:
    where the images put it rather than f_defo (``extrapolate/free_bodies.py``, ``refine_free_body``)."""

    c0: torch.Tensor
    v: torch.Tensor
    a: torch.Tensor
    w: torch.Tensor
    shift: torch.Tensor | None = None

    def __post_init__(self):
        if self.shift is None:
            self.shift = torch.zeros_like(self.c0)

    def as_tensor(self) -> torch.Tensor:
        """[FREE_BODY_NUMBERS]: c0, v, a, w, shift (as stored in a checkpoint)."""
        return torch.cat([self.c0, self.v, self.a, self.w, self.shift])

    @classmethod
    def from_tensor(cls, row: torch.Tensor) -> FreeBody:
        return cls(*row.double().reshape(FREE_BODY_NUMBERS // 3, 3))


def median_spacing(points: np.ndarray) -> float:
    """The median distance from each of ``points`` [N, 3] (N >= 2) to its nearest other point (scipy's
    cKDTree): the length that "so many Gaussian spacings" counts in."""
    from scipy.spatial import cKDTree

    return float(np.median(cKDTree(points).query(points, 2)[0][:, 1]))


def main_piece(points: torch.Tensor, spacings: float = 4.0) -> torch.Tensor:
    """[N] bool: the largest connected piece of ``points`` [N, 3], two points joined when they lie
    within ``spacings`` times the median nearest-neighbour spacing (scipy's cKDTree). A few Gaussians
    that f_defo moves with a body from elsewhere (`fallingball`: some from near the ground, a unit
    below the ball) are pieces of their own; in a body's hull they would pull its centroid to them."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    x = points.detach().double().cpu().numpy()
    if len(x) < 3:
        return torch.ones(len(x), dtype=torch.bool)
    tree = cKDTree(x)
    reach = spacings * max(median_spacing(x), 1e-12)
    graph = tree.sparse_distance_matrix(tree, reach, output_type="coo_matrix")
    _, piece = connected_components(graph, directed=False)
    return torch.as_tensor(piece == np.bincount(piece).argmax())


def centre_of_mass(points: torch.Tensor) -> torch.Tensor:
    """[3] float64: the centre of mass of the solid that the points [N, 3] bound, taken as their convex
    hull filled uniformly; the points' mean where they span no volume (fewer than 4, or flat).

    A free body turns about its centre of mass. The mean of its Gaussians is not that point: they lie
    on the surface the cameras saw, some sides more densely than others (`fallingball`'s ball, radius
    0.2: the mean 5 cm off its centre, the hull's centroid under 1 cm), and a free body turned about a
    wrong pivot sweeps that offset around as it spins."""
    from scipy.spatial import ConvexHull, QhullError

    p = points.detach().double().cpu()
    if len(p) < 4:
        return p.mean(0)
    try:
        hull = ConvexHull(p.numpy())
    except (QhullError, ValueError):
        return p.mean(0)
    origin = p[torch.as_tensor(hull.vertices)].mean(0)
    a, b, c = (p[torch.as_tensor(hull.simplices[:, k])] - origin for k in range(3))
    volume = torch.linalg.det(torch.stack([a, b, c], 1)).abs() / 6  # the tetrahedra on the origin
    if float(volume.sum()) <= 1e-12 * float((p - p.mean(0)).norm(dim=1).max()) ** 3:
        return p.mean(0)
    return origin + ((a + b + c) / 4 * volume[:, None]).sum(0) / volume.sum()


def fit_parabola(times: torch.Tensor, points: torch.Tensor, t0: float) -> tuple[torch.Tensor, ...]:
    """Least-squares ``c(t) = c0 + v s + a s^2 / 2`` (``s = t - t0``) through ``points`` [K, 3] at
    ``times`` [K]; returns (c0, v, a) in float64. Needs three distinct times."""
    s = times.double() - t0
    basis = torch.stack([torch.ones_like(s), s, 0.5 * s * s], 1)
    coef = torch.linalg.lstsq(basis, points.double()).solution
    return coef[0], coef[1], coef[2]


def fit_rigid_transform(
    a: torch.Tensor, b: torch.Tensor, weights: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(R [3, 3], T [3]) of the rotation and translation that best map the points ``a`` [N, 3] onto
    ``b`` [N, 3], ``b ~ R a + T`` (least squares, weighted by ``weights`` [N] when given; Kabsch via
    scipy's ``Rotation.align_vectors``; float64, a proper rotation)."""
    from scipy.spatial.transform import Rotation

    a, b = a.detach().double().cpu(), b.detach().double().cpu()
    if weights is None:
        ca, cb, w = a.mean(0), b.mean(0), None
    else:
        w = weights.detach().double().cpu().clamp_min(1e-12)
        ca, cb = (a * w[:, None]).sum(0) / w.sum(), (b * w[:, None]).sum(0) / w.sum()
        w = w.numpy()
    fitted, _ = Rotation.align_vectors((b - cb).numpy(), (a - ca).numpy(), weights=w)
    rotation = torch.as_tensor(fitted.as_matrix(), dtype=torch.float64)
    return rotation, cb - rotation @ ca


def pivot_path(pivot: torch.Tensor, at_t0: torch.Tensor, past: list[torch.Tensor]) -> torch.Tensor:
    """[K, 3] where the body point ``pivot`` (at ``t0``) is at each of the states ``past`` [K] of the
    body's points (``at_t0`` [N, 3] at ``t0``, each ``past[k]`` [N, 3]): carried by the rigid motion
    that best maps the points at ``t0`` onto them (``fit_rigid_transform``).

    A body's centre of mass recomputed from each state (its points' hull) is not that point: the hull is
    made by its outermost Gaussians, and a few of them that f_defo moves a little off the body move it.
    On `satellite`'s validation run the hulls' path gave a wing's centre an acceleration 0.9 off in a
    direction the truth has none; the rigid fits' path gives the whole body's motion (docs/PHYSICS.md,
    "The parts' paths from rigid fits")."""
    p = pivot.double().cpu()
    path = []
    for points in past:
        rotation, translation = fit_rigid_transform(at_t0, points)
        path.append(rotation @ p + translation)
    return torch.stack(path)


def fit_rigid_velocity(x: torch.Tensor, u: torch.Tensor, pivot: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """(v, w) of the rigid motion ``u = v + w x (x - pivot)`` that best fits the velocities ``u`` [N, 3]
    of the points ``x`` [N, 3] (least squares, float64)."""
    r = x.double() - pivot.double().to(x.device)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand(len(r), 3, 3)
    system = torch.cat([eye, -skew(r)], -1).reshape(-1, 6)
    v_w = torch.linalg.lstsq(system.cpu(), u.double().reshape(-1, 1).cpu()).solution[:, 0]
    return v_w[:3], v_w[3:]


def move(
    means: torch.Tensor, quats: torch.Tensor, body: FreeBody, s: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The Gaussians (``means``, ``quats`` at ``t0``) of ``body``, ``s`` later: turned by ``w s`` about
    the pivot, which has moved along its parabola."""
    turn = rodrigues(body.w * s)
    centre = body.c0 + body.shift + body.v * s + 0.5 * body.a * s * s
    dtype, dev = means.dtype, means.device
    new_means = (means.double() - body.c0.to(dev)) @ turn.to(dev).T + centre.to(dev)
    q = rotmat_to_quat(turn).to(dtype=quats.dtype, device=dev)[None].expand(len(quats), 4)
    return new_means.to(dtype), quat_multiply(q, quat_normalize(quats))


def apply_free_bodies(
    state: dict[str, torch.Tensor],
    start: dict[str, torch.Tensor],
    labels: torch.Tensor,
    bodies: torch.Tensor,
    s: float,
) -> dict[str, torch.Tensor]:
    """``state`` with the Gaussians of each free body moved from their ``start`` (its time ``t0``) ``s``
    later: ``labels`` [N] (0: left as they are, k: ``bodies[k - 1]``), ``bodies`` [K, 15] as
    ``FreeBody.as_tensor``."""
    means, quats = state["means"].clone(), quat_normalize(state["quats"]).clone()
    for k, row in enumerate(bodies):
        rows = labels == k + 1
        means[rows], quats[rows] = move(
            start["means"][rows], start["quats"][rows], FreeBody.from_tensor(row), s
        )
    return {**state, "means": means, "quats": quats}


def rigid_components(
    x: torch.Tensor,
    moved: torch.Tensor,
    u: torch.Tensor,
    speed_floor: float,
    neighbours: int = 8,
    min_size: int = 20,
) -> torch.Tensor:
    """[N] label of each point's rigid body, found without labels (0: none). The points ``moved`` [N]
    (bool) are joined to their ``neighbours`` nearest moved points where their relative velocity (from
    ``u`` [N, 3]) stays perpendicular to their separation, as a rigid pair's does (a stretching rate
    under a fifth of the relative speed plus ``speed_floor``); the connected groups of at least
    ``min_size`` points are the bodies, labelled 1, 2, ... by decreasing size. A necessary test, not a
    sufficient one: two bodies that slide past each other keep the distances of the pairs across the
    contact and may be joined, as may a part and what it hangs on by a hinge."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    labels = torch.zeros(len(x), dtype=torch.long)
    idx = torch.nonzero(moved.cpu()).squeeze(1).numpy()
    if len(idx) < max(min_size, 2):
        return labels
    points, vel = x.detach().double().cpu().numpy()[idx], u.detach().double().cpu().numpy()[idx]
    k = min(neighbours, len(idx) - 1)
    _, nn = cKDTree(points).query(points, k + 1)
    i, j = np.repeat(np.arange(len(idx)), k), nn[:, 1:].reshape(-1)
    sep, rel = points[i] - points[j], vel[i] - vel[j]
    stretch = np.abs((rel * sep).sum(1)) / np.maximum(np.linalg.norm(sep, axis=1), 1e-12)
    keep = stretch < 0.2 * np.linalg.norm(rel, axis=1) + speed_floor
    graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(len(idx), len(idx)))
    _, comp = connected_components(graph, directed=False)
    sizes = np.bincount(comp)
    order = [c for c in np.argsort(-sizes, kind="stable") if sizes[c] >= min_size]
    label_of = np.zeros(len(sizes), dtype=np.int64)
    label_of[order] = np.arange(1, len(order) + 1)
    labels[torch.as_tensor(idx)] = torch.as_tensor(label_of[comp])
    return labels


def _rigid_residual(x: torch.Tensor, u: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """[M] how far each velocity ``u`` [M, 3] of the points ``x`` [M, 3] is from the rigid motion fitted
    to the points ``rows`` (``fit_rigid_velocity`` about their mean)."""
    pivot = x[rows].mean(0)
    v, w = fit_rigid_velocity(x[rows], u[rows], pivot)
    return (u - v - torch.cross(w.expand_as(x), x - pivot, dim=-1)).norm(dim=1)


def _robust_rigid_fit(
    x: torch.Tensor, u: torch.Tensor, floor: float, rounds: int = 8, seeds: int = 4, share: float = 0.4
) -> tuple[torch.Tensor, torch.Tensor]:
    """([M] residual speeds, [M] inliers) of the points ``x`` [M, 3] (velocities ``u`` [M, 3]; float64)
    from the rigid motion that most of them follow: refitted on the points within three times the
    median residual (at least ``floor``) of the previous fit, from every point and from the ``share``
    of them nearest to each of ``seeds`` points spread over them (the farthest from those before);
    the start whose fit leaves the smallest residual at the ``share`` quantile of every point wins.
    From every point alone, two parts of about equal size (a chain's two links) give a compromise
    that fits neither, and claims both."""
    starts = [torch.ones(len(x), dtype=torch.bool)]
    near = max(3, int(share * len(x)))
    chosen = [0]
    for _ in range(seeds):
        gap = torch.cdist(x, x[chosen]).min(1).values
        chosen.append(int(gap.argmax()))
        start = torch.zeros(len(x), dtype=torch.bool)
        start[(x - x[chosen[-1]]).norm(dim=1).topk(near, largest=False).indices] = True
        starts.append(start)
    best = None
    for inliers in starts:
        residual = _rigid_residual(x, u, inliers)
        for _ in range(rounds):
            keep = residual < max(3 * float(residual[inliers].median()), floor)
            if torch.equal(keep, inliers) or int(keep.sum()) < 3:
                break
            inliers = keep
            residual = _rigid_residual(x, u, inliers)
        score = float(residual.quantile(share))
        if best is None or score < best[0] - 1e-12:
            best = (score, residual, inliers)
    return best[1], best[2]


def split_rigid(
    x: torch.Tensor,
    u: torch.Tensor,
    floor: float,
    neighbours: int = 8,
    min_size: int = 20,
    coverage: float = 0.95,
    max_parts: int = 8,
    rounds: int = 30,
) -> torch.Tensor:
    """[M] labels 1, 2, ... of the rigid parts of one connected group of points ``x`` [M, 3] moving at
    ``u`` [M, 3]: a body with parts on hinges (`satellite`'s wings and door) is connected, and
    ``rigid_components`` keeps it whole. The rigid motion that most of the points follow
    (``_robust_rigid_fit``) claims the largest connected set of points within six times the median
    residual of its inliers (at least ``floor``); the rest is split again, up to ``max_parts`` parts
    of at least ``min_size`` points. A group whose first motion explains a ``coverage`` fraction of
    it is one part. Last, each point joins the part, among its own and its ``neighbours``' parts,
    whose rigid motion fits its velocity best, pass after pass (up to ``rounds``) until none moves: the
    claims' threshold lets the first part take points of a hinged part near its hinge, where the two
    motions differ little, and one pass moves only the outermost of them."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    x, u = x.detach().double().cpu(), u.detach().double().cpu()
    labels = torch.zeros(len(x), dtype=torch.long)
    if len(x) < 2 * min_size:
        return labels + 1
    k = min(neighbours, len(x) - 1)
    _, nn = cKDTree(x.numpy()).query(x.numpy(), k + 1)
    i, j = np.repeat(np.arange(len(x)), k), nn[:, 1:].reshape(-1)
    for part in range(1, max_parts + 1):
        left = torch.nonzero(labels == 0).squeeze(1)
        if len(left) < min_size:
            break
        residual, inliers = _robust_rigid_fit(x[left], u[left], floor)
        close = residual < max(6 * float(residual[inliers].median()), floor)
        if part == 1 and float(close.double().mean()) >= coverage:
            return labels + 1
        member = torch.zeros(len(x), dtype=torch.bool)
        member[left[close]] = True
        keep = (member[i] & member[j]).numpy()
        graph = coo_matrix((np.ones(int(keep.sum())), (i[keep], j[keep])), shape=(len(x), len(x)))
        _, comp = connected_components(graph, directed=False)
        comp = torch.as_tensor(comp)
        sizes = torch.bincount(comp[member], minlength=int(comp.max()) + 1)
        largest = int(sizes.argmax())
        if int(sizes[largest]) < min_size:
            break
        labels[member & (comp == largest)] = part
    parts = int(labels.max())
    if parts == 0:
        return labels + 1
    lone = labels == 0
    if bool(lone.any()):  # a point left unlabelled starts in its nearest labelled point's part
        _, nearest = cKDTree(x[~lone].numpy()).query(x[lone].numpy(), 1)
        labels[lone] = labels[~lone][torch.as_tensor(nearest)]
    return _reassign(x, u, labels, torch.as_tensor(nn[:, 1:]), rounds)


def _reassign(
    x: torch.Tensor, u: torch.Tensor, labels: torch.Tensor, nn: torch.Tensor, rounds: int
) -> torch.Tensor:
    """``labels`` [M] (1, 2, ...) after up to ``rounds`` passes that move each point to the part, among
    its own and its neighbours' (``nn`` [M, k]), whose rigid motion (refitted every pass) fits its
    velocity best: a boundary that the first claim put inside a part moves a neighbour a pass, until it
    lies where the motions meet."""
    parts = int(labels.max())
    for _ in range(rounds):
        residual = torch.stack([_rigid_residual(x, u, labels == p) for p in range(1, parts + 1)], 1)
        around = torch.cat([labels[:, None], labels[nn]], 1)  # [M, k + 1]
        allowed = torch.zeros(len(x), parts + 1, dtype=torch.bool).scatter_(1, around, True)[:, 1:]
        new = residual.masked_fill(~allowed, float("inf")).argmin(1) + 1
        if torch.equal(new, labels):
            break
        labels = new
        kept = [p for p in range(1, parts + 1) if bool((labels == p).any())]
        if len(kept) < parts:  # a part emptied: renumber the rest 1, 2, ...
            relabel = torch.zeros(parts + 1, dtype=torch.long)
            relabel[torch.as_tensor(kept)] = torch.arange(1, len(kept) + 1)
            labels, parts = relabel[labels], len(kept)
    return labels


def isolation(x: torch.Tensor, group: torch.Tensor, still: torch.Tensor, quantile: float = 0.05) -> float:
    """How far the points ``group`` [N] (bool) of ``x`` [N, 3] lie from the ``still`` ones, in units of
    the points' median nearest-neighbour spacing: the ``quantile`` of the group's distances to the
    nearest still point (a few strays do not count). ``inf`` when nothing is still. A part on a hinge or
    a rail touches what holds it (a few spacings); a body in flight lies far from everything still."""
    from scipy.spatial import cKDTree

    points = x.detach().double().cpu().numpy()
    group, still = group.cpu().numpy(), still.cpu().numpy()
    if not still.any() or not group.any():
        return float("inf")
    distance = cKDTree(points[still]).query(points[group], 1)[0]
    return float(np.quantile(distance, quantile)) / max(median_spacing(points), 1e-12)
