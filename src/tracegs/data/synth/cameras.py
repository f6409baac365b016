"""Camera rig and train / val / test split of the synthetic scenes (the Dynamic Multipart protocol).

Cameras sit on a sphere around the object on a Fibonacci spiral between 15 and 60 degrees of
elevation, all looking at the centre of the object's bounds; the seed only turns the spiral about
the vertical axis. Matrices are camera-to-world in OpenGL / Blender axes (x right, y up, z backward),
as ``transforms_*.json`` stores them.

# C: cameras
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


@dataclass(frozen=True)
class Rig:
    """All cameras of a scene: poses, field of view, and which of them are held out."""

    c2w: np.ndarray  # [C, 4, 4] camera-to-world, OpenGL axes; camera id = row index
    camera_angle_x: float  # horizontal field of view, radians
    n_train: int  # cameras 0..n_train-1 train, the rest are the held-out (val) cameras


@dataclass(frozen=True)
class Split:
    """Which (camera, frame) pairs go into each of ``transforms_{train,val,test}.json``."""

    train: list[tuple[int, int]]
    val: list[tuple[int, int]]
    test: list[tuple[int, int]]

    def items(self):
        return (("train", self.train), ("val", self.val), ("test", self.test))


def default_val_views(views: int) -> int:
    """Held-out cameras: 3 of 15 as in the paper, 20% (at least one) in general."""
    return max(1, round(0.2 * views))


def default_train_frames(frames: int) -> int:
    """Training frames: the first 46 of 60 as in the paper (t <= 0.76), the same fraction in general."""
    return min(max(1, round(46 / 60 * frames)), frames - 1)


def look_at_opengl(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """[4, 4] camera-to-world with the camera at ``eye``, -z towards ``target``, y towards ``up``."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, true_up, back, eye
    return c2w


def fibonacci_band(n: int, seed: int, elev_min_deg: float = 15.0, elev_max_deg: float = 60.0) -> np.ndarray:
    """[n, 3] unit directions spread evenly (equal area) over the band of elevations, ordered from
    low to high; the azimuth of the first one comes from ``seed``."""
    z_lo, z_hi = np.sin(np.deg2rad(elev_min_deg)), np.sin(np.deg2rad(elev_max_deg))
    z = z_lo + (np.arange(n) + 0.5) / n * (z_hi - z_lo)
    azimuth = np.random.default_rng(seed).uniform(0.0, 2 * np.pi) + GOLDEN_ANGLE * np.arange(n)
    r = np.sqrt(1.0 - z**2)
    return np.stack([r * np.cos(azimuth), r * np.sin(azimuth), z], -1)


def held_out_last(n: int, n_val: int) -> np.ndarray:
    """Permutation of the spiral's n positions: train positions first, then ``n_val`` held-out ones
    spread along the spiral (so the validation views cover low and high elevations alike)."""
    held = sorted({min(n - 1, int((k + 0.5) * n / n_val)) for k in range(n_val)})
    train = [i for i in range(n) if i not in held]
    return np.array(train + held)


def make_rig(
    views: int, n_train: int, center, radius: float, seed: int, camera_angle_x: float = 0.6911
) -> Rig:
    """Cameras far enough that a sphere of ``radius`` about ``center`` fills the view with a margin.

    The default field of view is the one of the Blender / D-NeRF synthetic scenes."""
    distance = 1.05 * radius / np.sin(0.5 * camera_angle_x)
    dirs = fibonacci_band(views, seed)[held_out_last(views, views - n_train)]
    center = np.asarray(center, dtype=np.float64)
    c2w = np.stack([look_at_opengl(center + distance * d, center) for d in dirs])
    return Rig(c2w, float(camera_angle_x), n_train)


def make_split(views: int, frames: int, n_train_views: int, n_train_frames: int) -> Split:
    """Train: train cameras x first frames; val: held-out cameras x the same frames (interpolation);
    test: every camera x the remaining frames (extrapolation). Ordered by frame, then camera."""
    train_f, test_f = range(n_train_frames), range(n_train_frames, frames)
    return Split(
        train=[(c, f) for f in train_f for c in range(n_train_views)],
        val=[(c, f) for f in train_f for c in range(n_train_views, views)],
        test=[(c, f) for f in test_f for c in range(views)],
    )
