"""A body's shape for a simulator: the convex hull of its Gaussians' means (trimesh's, Qhull), and the
hull's mass, centre of mass and inertia at a density.

M: points, V: hull vertices, F: hull faces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FLAT = 1e-3
"""Smallest spread of a body's points across their thinnest direction, relative to their largest,
for their hull to have a volume as it is; a flatter body (a blade, a sheet) is given that thickness."""


@dataclass
class Hull:
    vertices: np.ndarray
    """[V, 3] in the world frame at the handover."""
    faces: np.ndarray
    """[F, 3] vertex indices, outward (counter-clockwise seen from outside)."""
    mass: float
    centre: np.ndarray
    """[3] its centre of mass."""
    inertia: np.ndarray
    """[3, 3] its inertia tensor about its centre of mass, world axes."""


def convex_hull(points: np.ndarray, density: float) -> Hull | None:
    """The hull of ``points`` [M, 3] with its mass properties at ``density``; None for fewer than 4
    points."""
    import trimesh

    points = np.asarray(points, dtype=np.float64)
    if len(points) < 4:
        return None
    centred = points - points.mean(0)
    _, sigma, axes = np.linalg.svd(centred, full_matrices=False)
    if sigma[-1] < FLAT * sigma[0]:  # thicken a flat part across its thinnest direction
        half = 0.5 * FLAT * float(np.abs(centred @ axes[0]).max())
        points = np.concatenate([points + half * axes[-1], points - half * axes[-1]])
    mesh = trimesh.convex.convex_hull(points)
    mesh.density = density
    return Hull(
        np.asarray(mesh.vertices, dtype=np.float64),
        np.asarray(mesh.faces, dtype=np.int64),
        float(mesh.mass),
        np.asarray(mesh.center_mass, dtype=np.float64),
        np.asarray(mesh.moment_inertia, dtype=np.float64),
    )


def axis_inertia(hull: Hull, axis: np.ndarray, pivot: np.ndarray, centre: np.ndarray | None = None) -> float:
    """The moment of inertia of ``hull`` about the line through ``pivot`` along the unit ``axis``, its
    centre of mass at ``centre`` (default: the hull's) and its inertia about it the hull's."""
    c = hull.centre if centre is None else centre
    r = c - pivot
    r_perp = r - (r @ axis) * axis
    return float(axis @ hull.inertia @ axis + hull.mass * (r_perp @ r_perp))
