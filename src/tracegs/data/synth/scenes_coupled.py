"""Synthetic scenes of motion kinds with several coupled degrees of freedom: a ball rolling in a bowl, a
gyroscope precessing on a pivot, a double pendulum, a disc held by three springs in a plane, and two
discs colliding on a table.

They follow the conventions of ``scenes.py`` (z up, within about a unit of the centre for t in
[0, 1.5], a static part in each, a texture per part) and are timed for the default protocol: each part
keeps moving through the future frames (t in (0.763, 1]) in a way its equations predict from the
training span, and no surface point moves more than about three pixels per frame at 128 px. The
motions are integrated with tight tolerances (:mod:`.mechanisms`) or in closed form (:mod:`.impacts`).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from . import geometry as g
from . import textures as tx
from .impacts import SlidingCollision
from .mechanisms import Gyroscope, HingedChain, PlanarSprings, RollingBall
from .motion import RigidMotion
from .parts import TEXTURE_SIZE, Part, Piece, SceneSpec, place, rot, scene_rng, turn_about

STATIC = RigidMotion("static")


def _along(mesh: g.Mesh, direction, origin) -> g.Mesh:
    """``mesh`` built along +z, turned to point along ``direction`` and moved to ``origin``."""
    d = np.asarray(direction, dtype=np.float64)
    d = d / np.linalg.norm(d)
    axis = np.cross([0.0, 0.0, 1.0], d)
    angle = float(np.arctan2(np.linalg.norm(axis), d[2]))
    R = rot(axis if np.linalg.norm(axis) > 1e-12 else (1.0, 0.0, 0.0), angle)
    return place(mesh, R, origin)


def rolling() -> SceneSpec:
    """A small ball (radius 0.08) rolling without slipping in a spherical bowl (radius 0.9), released
    off-centre with a sideways push: its centre swings round the bottom on a precessing ellipse."""
    r = lambda k: scene_rng("rolling", k)  # noqa: E731
    center, radius, ball_radius, g_ = (0.0, 0.0, 0.45), 0.9, 0.08, 29.0
    rim = np.radians(42)
    # a shell 0.03 thick, its profile outside up to the rim and inside back down: closed, facing out
    arc = np.linspace(0.0, rim, 16)
    outer = [((radius + 0.03) * np.sin(a), center[2] - (radius + 0.03) * np.cos(a)) for a in arc]
    inner = [(radius * np.sin(a), center[2] - radius * np.cos(a)) for a in arc[::-1]]
    profile = outer + inner
    bowl_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 8, (0.30, 0.34, 0.42), (0.80, 0.78, 0.70)), r(0), 0.25)
    stand_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 10, (0.35, 0.25, 0.18), (0.62, 0.50, 0.38)), r(1), 0.3)
    bowl = Part(
        "bowl",
        (
            Piece(g.lathe(profile, segments=64), bowl_tex),
            Piece(place(g.cylinder(0.3, 0.08), translation=(0.0, 0.0, -0.52)), stand_tex),
        ),
        STATIC,
    )
    rho, start = radius - ball_radius, np.radians(14)
    pivot = np.asarray(center) + rho * np.array([np.sin(start), 0.0, -np.cos(start)])
    colors = [(0.95, 0.35, 0.10), (0.15, 0.25, 0.75), (0.98, 0.95, 0.85), (0.15, 0.60, 0.30)]
    bands = tx.palette_bands(TEXTURE_SIZE, colors, along_u=True)
    rings = tx.stripes(TEXTURE_SIZE, 3, (1, 1, 1), (0.25, 0.25, 0.25), along_u=False, duty=0.3)
    motion = RollingBall(
        bowl_center=center,
        bowl_radius=radius,
        ball_radius=ball_radius,
        pivot=tuple(float(x) for x in pivot),
        linear_velocity=(0.0, 0.5, 0.0),
        normal_spin=0.0,
        gravity=g_,
    )
    ball_mesh = place(g.sphere(ball_radius, rings=16, segments=32), rot((1, 0, 0), 0.4), pivot)
    ball = Part("ball", (Piece(ball_mesh, tx.with_noise(bands * rings, r(2), 0.1)),), motion)
    return SceneSpec(
        "rolling", "a ball rolls without slipping round a spherical bowl; bowl static", (bowl, ball)
    )


def gyroscope() -> SceneSpec:
    """A spinning disc on an axle whose end rests on a pivot atop a post: gravity makes the axle
    precess about the vertical and nod (nutation) while the disc spins."""
    r = lambda k: scene_rng("gyroscope", k)  # noqa: E731
    pivot, arm, disc_radius, thickness = (0.0, 0.0, 0.2), 0.2, 0.26, 0.06
    post_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 6, (0.22, 0.24, 0.30), (0.60, 0.62, 0.66)), r(0), 0.3)
    base_tex = tx.wood(TEXTURE_SIZE, r(1), (0.80, 0.60, 0.38), (0.45, 0.26, 0.12))
    post = Part(
        "post",
        (
            Piece(place(g.cylinder(0.38, 0.06), translation=(0.0, 0.0, -0.47)), base_tex),
            Piece(place(g.cylinder(0.03, 0.62, segments=24), translation=(0.0, 0.0, -0.13)), post_tex),
        ),
        STATIC,
    )
    elevation = np.radians(10)
    axis = (float(np.cos(elevation)), 0.0, float(np.sin(elevation)))
    colors = [(0.95, 0.80, 0.15), (0.15, 0.15, 0.18), (0.85, 0.25, 0.20), (0.92, 0.92, 0.90)] * 2
    disc_tex = tx.with_noise(tx.sectors(TEXTURE_SIZE, colors[:-1], rim=(0.12, 0.12, 0.12)), r(2), 0.15)
    side_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 16, (0.15, 0.15, 0.18), (0.92, 0.92, 0.90)), r(3), 0.15)
    axle_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 6, (0.85, 0.85, 0.80), (0.55, 0.20, 0.15)), r(4), 0.2)
    at = lambda mesh, d: _along(mesh, axis, np.asarray(pivot) + d * np.asarray(axis))  # noqa: E731
    body = (
        Piece(at(g.cylinder(disc_radius, thickness), arm), disc_tex),
        Piece(at(g.cylinder(disc_radius + 0.002, thickness, caps=False), arm), side_tex),
        Piece(at(g.cylinder(0.022, 0.34, segments=16), 0.16), axle_tex),
    )
    motion = Gyroscope(
        pivot=pivot,
        axis=axis,
        com_distance=arm,
        # a solid disc, the axle's mass neglected
        transverse_inertia=disc_radius**2 / 4 + thickness**2 / 12 + arm**2,
        axial_inertia=disc_radius**2 / 2,
        spin=5.5,
        precession_rate=0.6,
        gravity=1.3,
    )
    return SceneSpec(
        "gyroscope",
        "a spinning disc on a pivot precesses and nods under gravity; post static",
        (post, Part("gyroscope", body, motion)),
    )


def doublependulum() -> SceneSpec:
    """Two uniform bars hinged end to end (parallel hinges along y) swinging from a static stand."""
    r = lambda k: scene_rng("doublependulum", k)  # noqa: E731
    pivot, lengths, masses = (0.0, 0.0, 0.5), (0.5, 0.4), (1.0, 0.8)
    wood = tx.wood(TEXTURE_SIZE, r(0), (0.80, 0.60, 0.38), (0.45, 0.26, 0.12))
    metal = tx.with_noise(tx.checker(TEXTURE_SIZE, 8, (0.22, 0.24, 0.30), (0.55, 0.58, 0.66)), r(1), 0.3)
    posts = [g.box((0.05, 0.05, 1.1), (0.0, sy * 0.2, -0.01)) for sy in (-1, 1)]
    stand = Part(
        "stand",
        (
            Piece(g.box((1.2, 0.6, 0.06), (0.0, 0.0, -0.58)), wood),
            Piece(g.merge(*posts, g.box((0.06, 0.45, 0.06), (0.0, 0.0, 0.55))), metal),
        ),
        STATIC,
    )
    chain = HingedChain(pivot, (0.0, 1.0, 0.0), lengths, masses, (0.5, 0.0), (0.0, 0.0), 12.0)
    joint = np.asarray(pivot)
    links = []
    textures = [
        tx.with_noise(tx.stripes(TEXTURE_SIZE, 8, (0.90, 0.30, 0.15), (0.98, 0.92, 0.80)), r(2), 0.2),
        tx.with_noise(tx.stripes(TEXTURE_SIZE, 6, (0.15, 0.35, 0.80), (0.90, 0.95, 0.98)), r(3), 0.2),
    ]
    for k, (length, tex) in enumerate(zip(lengths, textures, strict=True)):
        # built hanging straight down from its upper joint, then turned to its angle at t = 0;
        # the second bar sits in front of the first (y) so that they turn past each other
        bar = g.box((0.1, 0.06, length), (0.0, -0.065 * k, -length / 2))
        bar = turn_about(place(bar, translation=joint), chain.axis, chain.angles[k], joint)
        links.append(Part(f"link{k + 1}", (Piece(bar, tex),), replace(chain, link=k)))
        joint = joint + length * rot(chain.axis, chain.angles[k]) @ np.array([0.0, 0.0, -1.0])
    return SceneSpec(
        "doublependulum", "two bars hinged end to end swing under gravity; stand static", (stand, *links)
    )


def planarsprings() -> SceneSpec:
    """A disc on a table held by three springs (not drawn) to three posts, released off its equilibrium
    with a spin: it slides and turns in the plane (x, y and the angle coupled)."""
    r = lambda k: scene_rng("planarsprings", k)  # noqa: E731
    top, disc_radius, height, reach = -0.3, 0.2, 0.08, 0.68
    z = top + height / 2
    angles = np.radians([90.0, 210.0, 330.0])
    table_tex = tx.with_noise(
        tx.checker(TEXTURE_SIZE, 10, (0.30, 0.36, 0.30), (0.78, 0.80, 0.72)), r(0), 0.25
    )
    post_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 5, (0.85, 0.15, 0.10), (0.95, 0.85, 0.80)), r(1), 0.2)
    anchors = tuple((reach * float(np.cos(a)), reach * float(np.sin(a)), z) for a in angles)
    posts = [g.box((0.07, 0.07, 0.2), (x, y, top + 0.1)) for x, y, _ in anchors]
    table = Part(
        "table",
        (
            Piece(place(g.cylinder(0.82, 0.06), translation=(0.0, 0.0, top - 0.03)), table_tex),
            Piece(g.merge(*posts), post_tex),
        ),
        STATIC,
    )
    # at the equilibrium (the origin) each spring pulls radially with the same tension
    stiffness, tension = (25.0, 45.0, 70.0), 3.0
    center = np.array([0.18, -0.12, z])
    attachments = tuple(tuple(center + disc_radius * np.array([np.cos(a), np.sin(a), 0.0])) for a in angles)
    motion = PlanarSprings(
        pivot=tuple(float(x) for x in center),
        linear_velocity=(0.0, 0.5, 0.0),
        angular_velocity=2.0,
        anchors=anchors,
        attachments=attachments,
        stiffnesses=stiffness,
        rest_lengths=tuple(reach - disc_radius - tension / k for k in stiffness),
        mass=1.0,
        inertia=disc_radius**2 / 2,
        damping=0.2,
    )
    colors = [
        (0.15, 0.60, 0.30),
        (0.98, 0.95, 0.85),
        (0.85, 0.20, 0.45),
        (0.95, 0.75, 0.10),
        (0.20, 0.35, 0.85),
    ]
    disc_tex = tx.with_noise(tx.sectors(TEXTURE_SIZE, colors, rim=(0.12, 0.12, 0.12)), r(2), 0.15)
    side_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 12, (0.15, 0.15, 0.18), (0.92, 0.92, 0.90)), r(3), 0.15)
    disc = Part(
        "disc",
        (
            Piece(place(g.cylinder(disc_radius, height), translation=center), disc_tex),
            Piece(place(g.cylinder(disc_radius + 0.002, height, caps=False), translation=center), side_tex),
        ),
        motion,
    )
    return SceneSpec(
        "planarsprings",
        "a disc held by three springs slides and turns on a table; table static",
        (table, disc),
    )


def collision() -> SceneSpec:
    """A disc sliding on a table strikes a resting one off-centre at t = 0.278 (restitution 0.8); both
    slide on under friction, at angles, and stop at t = 1.29 and 1.73."""
    r = lambda k: scene_rng("collision", k)  # noqa: E731
    top, radius, height = -0.3, 0.14, 0.08
    z = top + height / 2
    table_tex = tx.wood(TEXTURE_SIZE, r(0), (0.55, 0.75, 0.55), (0.25, 0.45, 0.30))
    table = Part("table", (Piece(g.box((1.75, 1.45, 0.06), (-0.15, 0.15, top - 0.03)), table_tex),), STATIC)
    centers = ((-0.7, -0.15, z), (-0.1, 0.1, z))
    collide = dict(
        centers=centers,
        velocities=((1.5, 0.25, 0.0), (0.0, 0.0, 0.0)),
        radius=radius,
        masses=(1.0, 1.0),
        restitution=0.8,
        deceleration=0.7,
    )
    looks = [
        [(0.95, 0.45, 0.10), (0.98, 0.92, 0.80), (0.70, 0.10, 0.10)],
        [(0.15, 0.35, 0.80), (0.90, 0.95, 0.98), (0.10, 0.55, 0.60)],
    ]
    discs = []
    for k, (center, colors) in enumerate(zip(centers, looks, strict=True)):
        cap = tx.with_noise(tx.sectors(TEXTURE_SIZE, colors * 2, rim=(0.1, 0.1, 0.1)), r(1 + k), 0.15)
        side = tx.with_noise(tx.stripes(TEXTURE_SIZE, 12, colors[0], colors[1]), r(3 + k), 0.15)
        pieces = (
            Piece(place(g.cylinder(radius, height), translation=center), cap),
            Piece(place(g.cylinder(radius + 0.002, height, caps=False), translation=center), side),
        )
        discs.append(Part(("striker", "struck")[k], pieces, SlidingCollision(**collide, puck=k)))
    return SceneSpec(
        "collision",
        "a sliding disc strikes a resting one; both slide on and stop; table static",
        (table, *discs),
    )
