"""Procedural triangle meshes for the synthetic scenes, built with numpy alone (no asset files).

Every primitive returns a :class:`Mesh` whose hard edges have their own vertices, so the vertex
normals Mitsuba recomputes after every move are the right ones (flat faces stay flat, curved sides
stay smooth). UVs are laid out so that the procedural textures show their pattern on every face.

# V: vertices, F: triangles, M: sampled points
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Mesh:
    """An indexed triangle mesh with per-vertex texture coordinates."""

    vertices: np.ndarray  # [V, 3] float32
    uvs: np.ndarray  # [V, 2] float32, in [0, 1]
    faces: np.ndarray  # [F, 3] uint32, counter-clockwise seen from outside

    def __post_init__(self):
        if self.vertices.ndim != 2 or self.vertices.shape[1] != 3:
            raise ValueError(f"vertices must be [V, 3], got {self.vertices.shape}")
        if self.uvs.shape != (len(self.vertices), 2):
            raise ValueError(f"uvs must be [V, 2], got {self.uvs.shape}")
        if self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ValueError(f"faces must be [F, 3], got {self.faces.shape}")


def make_mesh(vertices, uvs, faces) -> Mesh:
    return Mesh(
        np.ascontiguousarray(vertices, dtype=np.float32),
        np.ascontiguousarray(uvs, dtype=np.float32),
        np.ascontiguousarray(faces, dtype=np.uint32),
    )


def merge(*meshes: Mesh) -> Mesh:
    """One mesh holding all triangles of ``meshes`` (texture coordinates are kept as they are)."""
    offsets = np.cumsum([0] + [len(m.vertices) for m in meshes[:-1]])
    return make_mesh(
        np.concatenate([m.vertices for m in meshes]),
        np.concatenate([m.uvs for m in meshes]),
        np.concatenate([m.faces + o for m, o in zip(meshes, offsets, strict=True)]),
    )


def transform(mesh: Mesh, matrix: np.ndarray) -> Mesh:
    """``mesh`` moved by the 4x4 affine ``matrix`` (a reflection would flip faces: not allowed)."""
    matrix = np.asarray(matrix, dtype=np.float64)
    if np.linalg.det(matrix[:3, :3]) <= 0:
        raise ValueError("transform must preserve orientation")
    v = mesh.vertices @ matrix[:3, :3].T + matrix[:3, 3]
    return make_mesh(v, mesh.uvs, mesh.faces)


def affine(rotation: np.ndarray | None = None, translation=(0.0, 0.0, 0.0), scale=1.0) -> np.ndarray:
    """4x4 matrix x -> rotation @ (scale * x) + translation."""
    m = np.eye(4)
    m[:3, :3] = (np.eye(3) if rotation is None else np.asarray(rotation)) * np.asarray(scale)
    m[:3, 3] = translation
    return m


def rotation_matrix(axis, angle: float) -> np.ndarray:
    """Rodrigues' formula: rotation by ``angle`` (radians, right-handed) about the unit ``axis``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def extrude(outline: np.ndarray, thickness: float) -> Mesh:
    """A prism: the convex polygon ``outline`` [K, 2] (counter-clockwise, in the xy plane) extruded
    symmetrically along z. Top and bottom get planar UVs over the outline's bounding box, so a
    texture covers each flat face once; the sides get a thin strip of the same texture."""
    outline = np.asarray(outline, dtype=np.float64)
    k = len(outline)
    lo, hi = outline.min(0), outline.max(0)
    uv_cap = (outline - lo) / np.maximum(hi - lo, 1e-9)
    h = thickness / 2
    fan = np.array([[0, i, i + 1] for i in range(1, k - 1)])
    top = make_mesh(np.c_[outline, np.full(k, h)], uv_cap, fan)
    bottom = make_mesh(np.c_[outline, np.full(k, -h)], uv_cap, fan[:, ::-1])
    sides = []
    for i in range(k):
        a, b = outline[i], outline[(i + 1) % k]
        quad = np.array([[*a, -h], [*b, -h], [*b, h], [*a, h]])
        u0, u1 = i / k, (i + 1) / k
        quad_uv = np.array([[u0, 0.0], [u1, 0.0], [u1, 0.05], [u0, 0.05]])
        sides.append(make_mesh(quad, quad_uv, [[0, 1, 2], [0, 2, 3]]))
    return merge(top, bottom, *sides)


def box(size, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Axis-aligned box; each of its six faces has its own vertices and the full texture."""
    half = np.asarray(size, dtype=np.float64) / 2
    eye = np.eye(3)
    quads = []
    for d in range(3):
        u, v = (d + 1) % 3, (d + 2) % 3  # e_u x e_v = e_d, so (u, v) is counter-clockwise seen from +d
        for sign in (1.0, -1.0):
            eu = eye[u] * half[u] * sign  # flipping u on the -d face keeps it counter-clockwise from outside
            ev = eye[v] * half[v]
            c = eye[d] * half[d] * sign
            corners = np.array([c - eu - ev, c + eu - ev, c + eu + ev, c - eu + ev])
            quads.append(make_mesh(corners, [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]]))
    return transform(merge(*quads), affine(translation=center))


def cylinder(radius: float, height: float, segments: int = 48, caps: bool = True) -> Mesh:
    """Cylinder along z, centred at the origin. Side UVs wrap once around (u) and along z (v); the
    caps get planar UVs centred on the axis, so a radial texture shows spokes turning with it."""
    ang = np.linspace(0.0, 2 * np.pi, segments + 1)
    ring = np.c_[radius * np.cos(ang), radius * np.sin(ang)]
    z = np.array([-height / 2, height / 2])
    v = np.array([[*p, zz] for zz in z for p in ring])
    uv = np.array([[a / (2 * np.pi), (zz > 0) * 1.0] for zz in z for a in ang])
    n = segments + 1
    f = [[i, i + 1, n + i + 1] for i in range(segments)] + [[i, n + i + 1, n + i] for i in range(segments)]
    parts = [make_mesh(v, uv, f)]
    if caps:
        disk = ring[:-1]
        disk_uv = 0.5 + 0.5 * disk / radius
        fan = np.array([[0, i, i + 1] for i in range(1, segments - 1)])
        parts.append(make_mesh(np.c_[disk, np.full(segments, height / 2)], disk_uv, fan))
        parts.append(make_mesh(np.c_[disk, np.full(segments, -height / 2)], disk_uv, fan[:, ::-1]))
    return merge(*parts)


def sphere(radius: float, rings: int = 24, segments: int = 48) -> Mesh:
    """UV sphere centred at the origin: u = longitude / 2pi, v = colatitude / pi. The poles are
    fanned (no zero-area triangles), so recomputed normals are defined everywhere."""
    theta = np.linspace(0.0, np.pi, rings + 1)
    phi = np.linspace(0.0, 2 * np.pi, segments + 1)
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    v = radius * np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    uv = np.stack([ph / (2 * np.pi), th / np.pi], -1)
    w = segments + 1
    faces = []
    for i in range(rings):
        for j in range(segments):
            a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
            if i > 0:
                faces.append([a, c, b])
            if i < rings - 1:
                faces.append([b, c, d])
    mesh = make_mesh(v.reshape(-1, 3), uv.reshape(-1, 2), faces)
    return _drop_unused(mesh)


def lathe(profile, segments: int = 48) -> Mesh:
    """The surface swept by turning the curve ``profile`` [K, 2] of (radius, z) points about z (a bowl,
    a vase): u = angle / 2pi, v = the point's index / (K - 1). Triangles on the axis (radius 0) are
    left out, as at the poles of :func:`sphere`."""
    profile = np.asarray(profile, dtype=np.float64)
    ang = np.linspace(0.0, 2 * np.pi, segments + 1)
    r, z = profile[:, 0, None], profile[:, 1, None]
    v = np.stack([r * np.cos(ang), r * np.sin(ang), np.broadcast_to(z, r.shape[:1] + ang.shape)], -1)
    vv = np.broadcast_to(np.linspace(0.0, 1.0, len(profile))[:, None], r.shape[:1] + ang.shape)
    uv = np.stack([np.broadcast_to(ang / (2 * np.pi), vv.shape), vv], -1)
    w, faces = segments + 1, []
    for i in range(len(profile) - 1):
        for j in range(segments):
            a, b, c, d = i * w + j, i * w + j + 1, (i + 1) * w + j, (i + 1) * w + j + 1
            if profile[i, 0] > 0:
                faces.append([a, b, c])
            if profile[i + 1, 0] > 0:
                faces.append([b, d, c])
    return _drop_unused(make_mesh(v.reshape(-1, 3), uv.reshape(-1, 2), faces))


def _drop_unused(mesh: Mesh) -> Mesh:
    """Remove vertices no triangle uses (Mitsuba warns about their undefined normals)."""
    used = np.unique(mesh.faces)
    remap = np.full(len(mesh.vertices), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return make_mesh(mesh.vertices[used], mesh.uvs[used], remap[mesh.faces])


def triangle_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F] area of each triangle."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=-1)


def sample_surface(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """[count, 3] points uniformly distributed over the surface area (area-weighted triangle
    choice, then uniform barycentric coordinates)."""
    v = mesh.vertices.astype(np.float64)
    areas = triangle_areas(v, mesh.faces.astype(np.int64))
    tri = rng.choice(len(areas), size=count, p=areas / areas.sum())
    r1, r2 = rng.random(count), rng.random(count)
    s = np.sqrt(r1)
    w = np.stack([1 - s, s * (1 - r2), s * r2], -1)  # [M, 3] barycentric, uniform on the triangle
    corners = v[mesh.faces[tri]]  # [M, 3, 3]
    return np.einsum("mk,mkd->md", w, corners)


def surface_area(mesh: Mesh) -> float:
    return float(triangle_areas(mesh.vertices.astype(np.float64), mesh.faces.astype(np.int64)).sum())
