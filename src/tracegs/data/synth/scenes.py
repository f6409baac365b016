"""The synthetic multi-part scenes: procedural geometry, textures and closed-form motion per part.

World axes: z up (as in Blender), units such that every scene stays within about one unit of the
origin for all t in [0, 1.5] (the extrapolation horizon). Motions are gentle on purpose: at 60
frames and 128 px the fastest surface point moves one to three pixels per frame, which a dynamic
Gaussian model can follow. Geometry and textures do not depend on the seed (the seed only moves the
cameras and the render noise), so a scene name always means the same object.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from . import geometry as g
from . import textures as tx
from .motion import RigidMotion
from .parts import TEXTURE_SIZE, Part, Piece, SceneSpec, place, rot, scene_rng
from .scenes_coupled import collision, doublependulum, gyroscope, planarsprings, rolling
from .scenes_varying import bounce, brake, pendulum, spring, turntable


def _rounded_paddle(r0: float, r1: float, width: float, n: int = 10) -> np.ndarray:
    """Convex outline of a fan blade along +x from r0 to r1: narrow root, round wide tip."""
    half = width / 2
    tip_c = r1 - half
    arc = np.linspace(-np.pi / 2, np.pi / 2, n)
    tip = np.c_[tip_c + half * np.cos(arc), half * np.sin(arc)]
    root = np.array([[r0, 0.45 * half]])
    root_lo = np.array([[r0, -0.45 * half]])
    return np.vstack([root_lo, tip, root])


def fan() -> SceneSpec:
    """A table fan pointing up: static base, pole and motor; three pitched blades spin about z."""
    r = lambda k: scene_rng("fan", k)  # noqa: E731
    body_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 8, (0.20, 0.27, 0.40), (0.45, 0.55, 0.70)), r(0), 0.3)
    base_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 10, (0.30, 0.30, 0.32), (0.60, 0.60, 0.58)), r(1), 0.3)
    base = place(g.cylinder(0.42, 0.08), translation=(0, 0, -0.71))
    pole = place(g.cylinder(0.05, 0.62, segments=24), translation=(0, 0, -0.36))
    motor = place(g.cylinder(0.14, 0.2), translation=(0, 0, 0.05))
    body = Part(
        "body",
        (Piece(base, base_tex), Piece(g.merge(pole, motor), body_tex)),
        RigidMotion("static"),
    )
    blade_colors = [((0.95, 0.45, 0.10), (0.98, 0.92, 0.80)), ((0.10, 0.65, 0.60), (0.90, 0.97, 0.95))]
    blade_colors.append(((0.85, 0.15, 0.45), (0.98, 0.88, 0.92)))
    pieces = []
    outline = _rounded_paddle(0.08, 0.8, 0.34)
    for i, (c0, c1) in enumerate(blade_colors):
        tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 6, c0, c1, along_u=True, duty=0.35), r(2 + i), 0.2)
        blade = g.extrude(outline, 0.025)
        # Pitch about the blade's long axis, then spread the three blades 120 degrees apart.
        blade = place(blade, rot((1, 0, 0), np.deg2rad(18)))
        blade = place(blade, rot((0, 0, 1), 2 * np.pi * i / 3), (0, 0, 0.21))
        pieces.append(Piece(blade, tex))
    hub_tex = tx.sectors(TEXTURE_SIZE, [(0.95, 0.80, 0.15), (0.15, 0.15, 0.18)] * 3)
    pieces.append(Piece(place(g.cylinder(0.11, 0.09), translation=(0, 0, 0.21)), hub_tex))
    blades = Part("blades", tuple(pieces), RigidMotion("rotation", axis=(0, 0, 1), angular_velocity=2.0))
    return SceneSpec("fan", "blades spin at constant angular velocity about z; body static", (body, blades))


def foldingchair() -> SceneSpec:
    """A chair on a static frame; seat, backrest and a side tray swing about three different hinges,
    each with constant angular acceleration."""
    r = lambda k: scene_rng("foldingchair", k)  # noqa: E731
    metal = tx.with_noise(tx.checker(TEXTURE_SIZE, 6, (0.18, 0.18, 0.20), (0.42, 0.42, 0.45)), r(0), 0.3)
    legs = [g.box((0.05, 0.05, 0.68), (sx * 0.28, sy * 0.28, -0.41)) for sx in (-1, 1) for sy in (-1, 1)]
    rails = [g.box((0.04, 0.6, 0.04), (sx * 0.28, 0, -0.55)) for sx in (-1, 1)]
    top_rails = [g.box((0.6, 0.04, 0.04), (0, sy * 0.28, -0.06)) for sy in (-1, 1)]
    frame = Part("frame", (Piece(g.merge(*legs, *rails, *top_rails), metal),), RigidMotion("static"))

    seat_tex = tx.wood(TEXTURE_SIZE, r(1), (0.85, 0.62, 0.35), (0.50, 0.28, 0.12))
    seat = Part(
        "seat",
        (Piece(g.box((0.62, 0.62, 0.05), (0.0, 0.0, -0.015)), seat_tex),),
        # Hinge along y at the back edge; about -y a positive angle lifts the front edge.
        RigidMotion("rotation", axis=(0, -1, 0), pivot=(-0.31, 0, 0.01), angular_acceleration=1.0),
    )
    back_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 5, (0.10, 0.30, 0.75), (0.85, 0.88, 0.95)), r(2), 0.2)
    backrest = Part(
        "backrest",
        (Piece(g.box((0.05, 0.6, 0.52), (-0.335, 0.0, 0.3)), back_tex),),
        # Hinge along y at the bottom of the backrest; about -y it reclines backwards (top to -x).
        RigidMotion(
            "rotation",
            axis=(0, -1, 0),
            pivot=(-0.335, 0, 0.04),
            angular_velocity=0.3,
            angular_acceleration=0.8,
        ),
    )
    tray_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 5, (0.15, 0.55, 0.20), (0.95, 0.85, 0.20)), r(3), 0.2)
    tray = Part(
        "side_tray",
        # Hangs down along the +y side of the frame in the rest pose.
        (Piece(g.box((0.4, 0.03, 0.3), (0.02, 0.33, -0.21)), tray_tex),),
        # Hinge along x at the tray's top edge; about +x a positive angle swings it out to +y and up.
        RigidMotion(
            "rotation",
            axis=(1, 0, 0),
            pivot=(0.02, 0.33, -0.06),
            angular_velocity=0.2,
            angular_acceleration=1.2,
        ),
    )
    return SceneSpec(
        "foldingchair",
        "seat, backrest and side tray rotate about three hinges with constant angular acceleration",
        (frame, seat, backrest, tray),
    )


def satellite() -> SceneSpec:
    """A box satellite drifting slowly; two solar wings and a hatch door open about three hinges
    that the drift carries along."""
    r = lambda k: scene_rng("satellite", k)  # noqa: E731
    drift = (0.12, 0.08, 0.06)
    foil = tx.with_noise(tx.checker(TEXTURE_SIZE, 12, (0.80, 0.60, 0.15), (0.95, 0.82, 0.40)), r(0), 0.45)
    dish_tex = tx.sectors(TEXTURE_SIZE, [(0.92, 0.92, 0.92), (0.70, 0.72, 0.78)] * 4, rim=(0.3, 0.3, 0.35))
    body = Part(
        "body",
        (
            Piece(g.box((0.5, 0.5, 0.5)), foil),
            Piece(place(g.cylinder(0.16, 0.04), translation=(0.0, 0.0, 0.33)), dish_tex),
            Piece(place(g.cylinder(0.03, 0.08, segments=16), translation=(0.0, 0.0, 0.27)), dish_tex),
        ),
        RigidMotion("translation", linear_velocity=drift),
    )
    solar = tx.cell_grid(TEXTURE_SIZE, 6, (0.08, 0.15, 0.45), (0.75, 0.78, 0.85), line_width=0.1)
    solar_b = tx.cell_grid(TEXTURE_SIZE, 4, (0.30, 0.08, 0.40), (0.85, 0.80, 0.75), line_width=0.12)
    # Wings hang folded against the +y and -y faces, hinged at their top edges along x; a positive
    # angle about +x (left) or -x (right) swings the lower edge outwards.
    left = Part(
        "left_wing",
        (Piece(g.box((0.46, 0.02, 0.46), (0.0, 0.27, 0.0)), tx.with_noise(solar, r(1), 0.15)),),
        RigidMotion(
            "rotation+translation",
            axis=(1, 0, 0),
            pivot=(0.0, 0.27, 0.23),
            angular_velocity=1.0,
            linear_velocity=drift,
        ),
    )
    right = Part(
        "right_wing",
        (Piece(g.box((0.46, 0.02, 0.46), (0.0, -0.27, 0.0)), tx.with_noise(solar_b, r(2), 0.15)),),
        RigidMotion(
            "rotation+translation",
            axis=(-1, 0, 0),
            pivot=(0.0, -0.27, 0.23),
            angular_velocity=0.8,
            angular_acceleration=0.2,
            linear_velocity=drift,
        ),
    )
    door_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 4, (0.85, 0.10, 0.10), (0.96, 0.96, 0.96)), r(3), 0.15)
    # The hatch covers the middle of the +x face; hinged along z at its +y edge, it swings outwards.
    door = Part(
        "door",
        (Piece(g.box((0.02, 0.3, 0.3), (0.265, 0.0, 0.0)), door_tex),),
        RigidMotion(
            "rotation+translation",
            axis=(0, 0, 1),
            pivot=(0.265, 0.15, 0.0),
            angular_velocity=1.2,
            linear_velocity=drift,
        ),
    )
    return SceneSpec(
        "satellite",
        "body drifts at constant velocity; two wings and a door open about hinges carried by the drift",
        (body, left, right, door),
    )


def fallingball() -> SceneSpec:
    """A spinning ball thrown over a static slab: projectile under gravity plus constant spin."""
    r = lambda k: scene_rng("fallingball", k)  # noqa: E731
    slab_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 8, (0.35, 0.35, 0.38), (0.80, 0.80, 0.78)), r(0), 0.25)
    slab = Part(
        "ground", (Piece(g.box((1.3, 0.7, 0.06), (0.0, 0.0, -0.93)), slab_tex),), RigidMotion("static")
    )
    colors = [(0.90, 0.15, 0.15), (0.98, 0.85, 0.15), (0.15, 0.45, 0.90), (0.98, 0.98, 0.98)]
    bands = tx.palette_bands(TEXTURE_SIZE, colors * 2, along_u=True)
    rings = tx.stripes(TEXTURE_SIZE, 4, (1, 1, 1), (0.35, 0.35, 0.35), along_u=False, duty=0.15)
    ball_tex = tx.with_noise(bands * rings, r(1), 0.15)
    center = (-0.55, 0.0, 0.05)
    ball = Part(
        "ball",
        (Piece(place(g.sphere(0.2), rot((1, 0, 0), 0.4), center), ball_tex),),
        RigidMotion(
            "projectile",
            axis=(0.2, 1.0, 0.3),
            pivot=center,
            angular_velocity=4.0,
            linear_velocity=(0.65, 0.0, 1.0),
            linear_acceleration=(0.0, 0.0, -2.0),
        ),
    )
    return SceneSpec(
        "fallingball", "ball thrown under gravity with constant spin; ground static", (slab, ball)
    )


def slider() -> SceneSpec:
    """A carriage accelerating along a static rail while a wheel behind it turns."""
    r = lambda k: scene_rng("slider", k)  # noqa: E731
    rail_tex = tx.with_noise(tx.stripes(TEXTURE_SIZE, 12, (0.25, 0.25, 0.28), (0.65, 0.66, 0.70)), r(0), 0.3)
    rail = Part(
        "rail",
        (
            Piece(
                g.merge(
                    g.box((1.6, 0.3, 0.08), (0.0, 0.0, -0.3)),
                    g.box((0.06, 0.3, 0.16), (-0.78, 0.0, -0.18)),
                    g.box((0.06, 0.3, 0.16), (0.78, 0.0, -0.18)),
                    g.box((0.08, 0.08, 0.5), (0.0, -0.35, -0.09)),
                ),
                rail_tex,
            ),
        ),
        RigidMotion("static"),
    )
    cart_tex = tx.with_noise(tx.checker(TEXTURE_SIZE, 4, (0.95, 0.50, 0.05), (0.20, 0.12, 0.08)), r(1), 0.2)
    carriage = Part(
        "carriage",
        (Piece(g.box((0.3, 0.26, 0.2), (-0.6, 0.0, -0.16)), cart_tex),),
        RigidMotion("translation", linear_velocity=(0.1, 0.0, 0.0), linear_acceleration=(0.9, 0.0, 0.0)),
    )
    # Four different colours between white spokes: no rotational symmetry, so the angle is unambiguous.
    spokes = [(0.15, 0.60, 0.30), (0.20, 0.35, 0.85), (0.85, 0.20, 0.20), (0.95, 0.75, 0.10)]
    white = (0.95, 0.95, 0.90)
    wheel_tex = tx.sectors(TEXTURE_SIZE, [c for s in spokes for c in (s, white)], rim=(0.15, 0.15, 0.15))
    wheel_center = (0.0, -0.44, 0.2)
    wheel = Part(
        "wheel",
        # A disk in the xz plane behind the rail (its axis along y).
        (Piece(place(g.cylinder(0.3, 0.06), rot((1, 0, 0), np.pi / 2), wheel_center), wheel_tex),),
        RigidMotion(
            "rotation", axis=(0, 1, 0), pivot=wheel_center, angular_velocity=2.5, angular_acceleration=-0.6
        ),
    )
    return SceneSpec(
        "slider", "carriage translates with constant acceleration; wheel rotates", (rail, carriage, wheel)
    )


SCENES: dict[str, Callable[[], SceneSpec]] = {
    "fan": fan,
    "foldingchair": foldingchair,
    "satellite": satellite,
    "fallingball": fallingball,
    "slider": slider,
    "pendulum": pendulum,
    "spring": spring,
    "brake": brake,
    "bounce": bounce,
    "turntable": turntable,
    "rolling": rolling,
    "gyroscope": gyroscope,
    "doublependulum": doublependulum,
    "planarsprings": planarsprings,
    "collision": collision,
}
"""Scene name -> builder of its :class:`SceneSpec`."""


def get_scene(name: str) -> SceneSpec:
    if name not in SCENES:
        raise ValueError(f"unknown synthetic scene {name!r}; available: {', '.join(SCENES)}")
    return SCENES[name]()
