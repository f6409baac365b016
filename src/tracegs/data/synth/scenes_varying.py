"""Synthetic scenes whose forces are not constant: a damped pendulum, a mass on a spring, a wheel
braking to rest, a ball bouncing on the floor, a box spinning on a turntable.

They follow the conventions of ``scenes.py`` (z up, within about a unit of the centre for t in
[0, 1.5], a static part in each, a texture per part) and are timed for the default protocol, whose
training span ends at t = 45/59 = 0.763: the behaviour a constant acceleration cannot extrapolate
happens in the future frames (the pendulum and the mass turn back, the wheel stops, the ball bounces
again, the box keeps bending its path round the circle).
"""

from __future__ import annotations

import numpy as np

from . import geometry as g
from . import textures as tx
from .motion import RigidMotion
from .parts import TEXTURE_SIZE, Part, Piece, SceneSpec, place, rot, scene_rng, turn_about
from .varying import Bouncing, Carried, DampedRotation, DampedTranslation, FrictionStop

HINGE = (0.0, 0.0, 0.52)
"""The pendulum's pivot: the axle under the stand's top bar."""


def _upright(radius: float, thickness: float, center) -> g.Mesh:
    """A disk standing in the xz plane (axis along y) centred at ``center``."""
    return place(g.cylinder(radius, thickness), rot((1, 0, 0), np.pi / 2), center)


def pendulum() -> SceneSpec:
    """A damped pendulum swinging in the xz plane about a horizontal hinge along y, between the two
    posts of a static stand: theta(t) = 0.7 e^{-0.5 t} cos(4.975 t - 1.4) from hanging straight down."""
    r = lambda k: scene_rng("pendulum", k)  # noqa: E731
    wood = tx.wood(TEXTURE_SIZE, r(0), (0.80, 0.60, 0.38), (0.45, 0.26, 0.12))
    metal = tx.with_noise(tx.checker(TEXTURE_SIZE, 8, (0.22, 0.24, 0.30), (0.55, 0.58, 0.66)), r(1), 0.3)
    posts = [g.box((0.05, 0.05, 1.3), (0.0, sy * 0.24, -0.07)) for sy in (-1, 1)]
    stand = Part(
        "stand",
        (
            Piece(g.box((1.4, 0.62, 0.06), (0.0, 0.0, -0.75)), wood),
            Piece(g.merge(*posts, g.box((0.06, 0.53, 0.06), (0.0, 0.0, 0.55))), metal),
        ),
        RigidMotion("static"),
    )
    swing = DampedRotation(amplitude=0.7, phase=-1.4, natural_frequency=5.0, damping_ratio=0.1, pivot=HINGE)
    rod_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 8, (0.85, 0.80, 0.70), (0.25, 0.22, 0.20)), r(2), 0.2)
    bob_colors = [(0.90, 0.20, 0.15), (0.98, 0.95, 0.85), (0.15, 0.40, 0.85), (0.95, 0.75, 0.10)]
    bob_tex = tx.with_noise(tx.sectors(TEXTURE_SIZE, bob_colors, rim=(0.12, 0.12, 0.12)), r(3), 0.15)
    # Built hanging straight down, then turned to the angle of t = 0 (the rest pose of the data).
    rest = float(swing.value(0.0)[0])
    rod = turn_about(g.box((0.04, 0.04, 0.64), (0.0, 0.0, 0.20)), swing.axis, rest, HINGE)
    bob = turn_about(_upright(0.17, 0.08, (0.0, 0.0, -0.26)), swing.axis, rest, HINGE)
    arm = Part("pendulum", (Piece(rod, rod_tex), Piece(bob, bob_tex)), swing)
    return SceneSpec(
        "pendulum", "a damped pendulum swings about a horizontal hinge; stand static", (stand, arm)
    )


def spring() -> SceneSpec:
    """A block on a spring (not drawn) sliding along x on a static rail, released from rest 0.35 from
    its equilibrium: x(t) = 0.35 e^{-0.56 t} cos(6.978 t + phi), phi making x'(0) = 0."""
    r = lambda k: scene_rng("spring", k)  # noqa: E731
    rail_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 14, (0.28, 0.30, 0.34), (0.70, 0.72, 0.76)), r(0), 0.3)
    wall_tex = tx.with_noise(
        tx.cell_grid(TEXTURE_SIZE, 4, (0.55, 0.25, 0.20), (0.85, 0.82, 0.78)), r(1), 0.25
    )
    base = Part(
        "rail",
        (
            Piece(g.box((1.8, 0.36, 0.08), (0.0, 0.0, -0.30)), rail_tex),
            Piece(g.box((0.06, 0.36, 0.40), (-0.87, 0.0, -0.06)), wall_tex),  # where the spring is fixed
        ),
        RigidMotion("static"),
    )
    zeta = 0.08
    oscillation = DampedTranslation(
        amplitude=0.35,
        phase=-float(np.arctan(zeta / np.sqrt(1 - zeta**2))),  # at rest at t = 0
        natural_frequency=7.0,
        damping_ratio=zeta,
        direction=(1.0, 0.0, 0.0),
    )
    x0 = float(oscillation.value(0.0)[0])  # the equilibrium is x = 0
    block_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 4, (0.10, 0.55, 0.35), (0.95, 0.90, 0.55)), r(2), 0.2)
    block = Part("block", (Piece(g.box((0.30, 0.28, 0.24), (x0, 0.0, -0.14)), block_tex),), oscillation)
    return SceneSpec("spring", "a block oscillates on a damped spring along a static rail", (base, block))


def brake() -> SceneSpec:
    """A wheel on a static stand braking at a constant rate, w = 3.8 - 4.0 t, until it stops at
    t = 0.95, then held still."""
    r = lambda k: scene_rng("brake", k)  # noqa: E731
    stand_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 6, (0.25, 0.25, 0.28), (0.62, 0.62, 0.60)), r(0), 0.3)
    pad_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 5, (0.85, 0.15, 0.10), (0.95, 0.85, 0.80)), r(1), 0.2)
    center = (0.0, 0.0, 0.05)
    stand = Part(
        "stand",
        (
            Piece(
                g.merge(
                    g.box((0.9, 0.5, 0.06), (0.0, 0.0, -0.62)),
                    g.box((0.08, 0.08, 0.64), (0.0, -0.10, -0.27)),
                    place(g.cylinder(0.05, 0.22), rot((1, 0, 0), np.pi / 2), center),  # the axle
                ),
                stand_tex,
            ),
            Piece(g.box((0.14, 0.16, 0.07), (0.0, 0.0, 0.515)), pad_tex),  # the brake pad on the rim
        ),
        RigidMotion("static"),
    )
    spokes = [(0.15, 0.60, 0.30), (0.90, 0.45, 0.10), (0.20, 0.35, 0.85), (0.85, 0.20, 0.45)]
    white = (0.95, 0.95, 0.90)
    wheel_tex = tx.sectors(TEXTURE_SIZE, [c for s in spokes for c in (s, white)], rim=(0.12, 0.12, 0.12))
    wheel = Part(
        "wheel",
        (Piece(_upright(0.42, 0.08, center), tx.with_noise(wheel_tex, r(2), 0.15)),),
        FrictionStop(axis=(0, 1, 0), pivot=center, angular_velocity=3.8, angular_acceleration=-4.0),
    )
    return SceneSpec("brake", "a wheel brakes at a constant rate to a stop; stand static", (stand, wheel))


def bounce() -> SceneSpec:
    """A spinning ball bouncing on a static floor slab: g = 8, restitution 0.7, contacts at
    t = 0.375, 0.848, 1.178, 1.410, ...; the horizontal velocity 0.35 along x stays."""
    r = lambda k: scene_rng("bounce", k)  # noqa: E731
    floor_tex = tx.with_noise(
        tx.checker(TEXTURE_SIZE, 10, (0.30, 0.36, 0.30), (0.78, 0.80, 0.72)), r(0), 0.25
    )
    floor = Part(
        "floor", (Piece(g.box((1.5, 0.7, 0.06), (0.0, 0.0, -0.53)), floor_tex),), RigidMotion("static")
    )
    radius, start = 0.16, (-0.45, 0.0, 0.11)
    colors = [(0.95, 0.50, 0.10), (0.20, 0.20, 0.70), (0.98, 0.98, 0.95), (0.20, 0.70, 0.35)]
    bands = tx.palette_bands(TEXTURE_SIZE, colors * 2, along_u=True)
    rings = tx.stripes(TEXTURE_SIZE, 5, (1, 1, 1), (0.30, 0.30, 0.30), along_u=False, duty=0.2)
    ball = Part(
        "ball",
        (
            Piece(
                place(g.sphere(radius), rot((1, 0, 0), 0.5), start), tx.with_noise(bands * rings, r(1), 0.15)
            ),
        ),
        Bouncing(
            pivot=start,
            linear_velocity=(0.35, 0.0, 0.3),
            gravity=8.0,
            floor_height=-0.5 + radius,
            restitution=0.7,
            axis=(0.0, 1.0, 0.0),
            angular_velocity=3.0,
        ),
    )
    return SceneSpec(
        "bounce", "a spinning ball bounces on the floor, losing height; floor static", (floor, ball)
    )


def turntable() -> SceneSpec:
    """A box spinning about its own vertical axis (2.5 rad per unit t) on a turntable that turns about
    the scene's vertical axis (2.0): the box's centre goes round a circle of radius 0.36."""
    r = lambda k: scene_rng("turntable", k)  # noqa: E731
    base_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 16, (0.30, 0.30, 0.33), (0.62, 0.60, 0.58)), r(0), 0.3)
    base = Part(
        "base",
        (Piece(place(g.cylinder(0.5, 0.3), translation=(0, 0, -0.45)), base_tex),),
        RigidMotion("static"),
    )
    disc_colors = [(0.95, 0.85, 0.20), (0.15, 0.15, 0.18), (0.85, 0.30, 0.20), (0.92, 0.92, 0.90)] * 3
    # sectors out to the edge: a ring of one colour would turn unseen, its ground-truth motion not in the images
    disc_tex = tx.with_noise(tx.sectors(TEXTURE_SIZE, disc_colors[:-1]), r(1), 0.15)
    spin = RigidMotion("rotation", axis=(0, 0, 1), angular_velocity=2.0)
    # and its thin side in stripes (the side takes one column of the cap's texture per angle: too smooth to see turn)
    side_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 24, (0.15, 0.15, 0.18), (0.92, 0.92, 0.90)), r(3), 0.15)
    disc = Part(
        "turntable",
        (
            Piece(place(g.cylinder(0.62, 0.05), translation=(0, 0, -0.275)), disc_tex),
            Piece(place(g.cylinder(0.622, 0.05, caps=False), translation=(0, 0, -0.275)), side_tex),
        ),
        spin,
    )
    center = (0.36, 0.0, -0.14)
    box_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 3, (0.20, 0.55, 0.85), (0.95, 0.60, 0.70)), r(2), 0.35)
    box = Part(
        "box",
        (Piece(g.box((0.26, 0.18, 0.22), center), box_tex),),
        Carried(
            spin, RigidMotion("rotation", axis=(0, 0, 1), pivot=center, angular_velocity=2.5), parent_part=2
        ),
    )
    return SceneSpec("turntable", "a box spins on a turning turntable; base static", (base, disc, box))
