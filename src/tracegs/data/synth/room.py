"""A textured room round a synthetic scene (``tracegs synth --textured-surroundings``).

A floor just under the scene's bounds and four walls far behind the cameras, open at the top so the
sun still lights the scene. Their pattern (coloured value noise posterised into sharp-edged blobs, random at every
scale, nothing repeating) gives a calibration something to match between the cameras, as the walls
and floor of a real room do (``tracegs import`` recovers the synthetic rig from its videos). The room
is no part: its pixels are background (id 0) in ``gt/masks``, and without the option the scenes are
rendered as before, byte for byte.
"""

from __future__ import annotations

import numpy as np

from . import geometry as g
from . import textures as tx
from .parts import Piece

ROOM_TEXTURE = 1024
"""Texels along a side of the floor's and each wall's texture."""


def room_texture(rng: np.random.Generator, size: int = ROOM_TEXTURE) -> np.ndarray:
    """[size, size, 3] linear RGB: each channel its own fractal noise, posterised into six levels
    (sharp-edged blobs of every size, which feature detectors find at every scale)."""
    channels = [tx.fractal_noise(size, rng, octaves=5, base_cells=16) for _ in range(3)]
    srgb = 0.1 + 0.8 * np.floor(np.stack(channels, -1) * 5.999) / 5
    return tx.srgb_to_linear(srgb).astype(np.float32)


def _quad(corners) -> g.Mesh:
    return g.make_mesh(corners, [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]])


def room_pieces(aabb: np.ndarray, center, distance: float, seed: int = 0) -> tuple[Piece, ...]:
    """The floor at the bottom of ``aabb`` [2, 3] (less a hair) and four walls at twice the camera
    ``distance`` from ``center`` [3], up to one ``distance`` above it."""
    rng = np.random.default_rng([seed, 1009])
    cx, cy, cz = (float(v) for v in center)
    half = 2.0 * distance
    floor = float(aabb[0, 2]) - 0.01 * distance
    top = cz + distance
    x0, x1, y0, y1 = cx - half, cx + half, cy - half, cy + half
    quads = [
        [[x0, y0, floor], [x1, y0, floor], [x1, y1, floor], [x0, y1, floor]],
        [[x0, y0, floor], [x1, y0, floor], [x1, y0, top], [x0, y0, top]],
        [[x1, y0, floor], [x1, y1, floor], [x1, y1, top], [x1, y0, top]],
        [[x1, y1, floor], [x0, y1, floor], [x0, y1, top], [x1, y1, top]],
        [[x0, y1, floor], [x0, y0, floor], [x0, y0, top], [x0, y1, top]],
    ]
    return tuple(Piece(_quad(q), room_texture(rng)) for q in quads)
