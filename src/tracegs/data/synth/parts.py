"""The pieces a synthetic scene is made of: textured meshes, rigid parts with their motion, and the
helpers the scene builders share (``scenes.py``, ``scenes_varying.py``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import geometry as g
from .kinematics import Motion

TEXTURE_SIZE = 256


@dataclass(frozen=True)
class Piece:
    """A mesh with one texture; a part is made of one or more pieces moving together."""

    mesh: g.Mesh
    texture: np.ndarray  # [H, W, 3] linear RGB float32


@dataclass(frozen=True)
class Part:
    """A rigid part: its rest-pose pieces and its motion. Mask id = position in the scene + 1."""

    name: str
    pieces: tuple[Piece, ...]
    motion: Motion


@dataclass(frozen=True)
class SceneSpec:
    name: str
    description: str
    parts: tuple[Part, ...]

    def part_mesh(self, index: int) -> g.Mesh:
        """All pieces of part ``index`` as one mesh (for sampling and bounds)."""
        return g.merge(*(p.mesh for p in self.parts[index].pieces))


def scene_rng(name: str, k: int) -> np.random.Generator:
    """Fixed generator per scene and texture, so textures never depend on the caller's seed."""
    return np.random.default_rng([sum(map(ord, name)), k])


def rot(axis, angle) -> np.ndarray:
    return g.rotation_matrix(axis, angle)


def place(mesh: g.Mesh, rotation=None, translation=(0.0, 0.0, 0.0)) -> g.Mesh:
    return g.transform(mesh, g.affine(rotation, translation))


def turn_about(mesh: g.Mesh, axis, angle: float, pivot) -> g.Mesh:
    """``mesh`` rotated by ``angle`` about the line through ``pivot`` along ``axis``."""
    R = rot(axis, angle)
    pivot = np.asarray(pivot, dtype=np.float64)
    return place(mesh, R, pivot - R @ pivot)
