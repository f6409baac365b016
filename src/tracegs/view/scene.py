"""What the viewer shows, apart from the web server: the Gaussians at any time under either motion
model, one rendered frame (optionally with the segments painted over it), the run's segmentation and
the dataset's cameras.

N: Gaussians, K: segments, H, W: image size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..data.cameras import Camera
from ..data.scene import DatasetError, available_splits, load_scene
from ..extrapolate import Predictor
from ..segment.command import load_segments
from ..segment.masks import colours, overlay

MOTIONS = {"TRACE physics": "trace", "f_defo alone": "f_defo", "MuJoCo model": "simulator"}
"""The viewer's motion models by their GUI label: ``trace`` (f_defo up to the handover, then the
learned physics: what TRACE predicts), ``f_defo`` (the deformation field queried at every time,
past its training span too: what DefGS predicts) and ``simulator`` (the run's MuJoCo model, ``tracegs
export --mjcf``, run from the handover; with ``tracegs view --simulator``)."""


@dataclass
class Segments:
    """A run's segmentation as the viewer paints it."""

    labels: torch.Tensor  # [N] long in 0 .. K-1
    k: int
    palette: np.ndarray  # [K, 3] RGB in [0, 1]


def find_segments(run: Path, n: int) -> tuple[Segments | None, str]:
    """(the segmentation stored in ``run`` by ``tracegs segment``, or None; a line saying why not) for
    a model of ``n`` Gaussians."""
    try:
        stored = load_segments(run)
    except FileNotFoundError:
        return None, f"no segmentation in {run} (`tracegs segment --run {run} --auto-k` makes one)"
    labels = stored["labels"].long()
    if labels.shape[0] != n:
        return None, f"{run}: the segmentation has {labels.shape[0]} labels for {n} Gaussians; segment again"
    k = int(stored["k"])
    return Segments(labels, k, colours(k, bool(stored["has_static"]))), ""


@torch.no_grad()
def render_view(
    predictor: Predictor, gaussians: dict, camera: Camera, segments: Segments | None = None
) -> np.ndarray:
    """uint8 [H, W, 3]: the Gaussians ``gaussians`` (geometry at some time) seen by ``camera``, each
    pixel tinted by its segment's colour when ``segments`` is given."""
    camera = camera.to(predictor.device)
    image = predictor.render(camera, gaussians=gaussians).cpu().numpy()
    if segments is not None:
        label_image, _ = predictor.render_labels(camera, segments.labels, segments.k, gaussians=gaussians)
        image = overlay(image, label_image, segments.palette)
    return (np.clip(image, 0.0, 1.0) * 255 + 0.5).astype(np.uint8)


def phase(t: float, t_max: float, motion: str) -> str:
    """One markdown line saying whether time ``t`` is observed (inside the training span, up to
    ``t_max``) or predicted, and by which motion model."""
    if t <= t_max:
        return f"t = {t:.3f}: **observed** (training span 0 - {t_max:.3f})"
    how = {
        "trace": "learned physics (TRACE)",
        "simulator": "run's MuJoCo model (its parts and identified models)",
    }.get(motion, "f_defo past its training span (DefGS)")
    return f"t = {t:.3f}: **predicted** by the {how}, {t - t_max:.3f} after the training end"


@dataclass
class DatasetCameras:
    """The cameras of a scene folder, each pose once (in the first split that has it: a camera filmed
    in training and in the future is a training camera), and the scene's background."""

    cameras: dict[str, list[Camera]]  # split -> cameras
    background: tuple[float, float, float]
    note: str
    """Empty, or a line saying why no cameras are shown."""


def dataset_cameras(data: Path, downscale: int = 1) -> DatasetCameras:
    """The cameras of every split of the scene folder ``data``; a missing or unreadable folder gives no
    cameras and a note (the viewer serves the run without them)."""
    splits = available_splits(data)
    if not splits:
        return DatasetCameras({}, (1.0, 1.0, 1.0), f"no scene at {data}: dataset cameras not shown")
    cameras, background, seen = {}, (1.0, 1.0, 1.0), set()
    try:
        for split in splits:
            scene = load_scene(data, split, downscale)
            background = scene.background if split == "train" else background
            cameras[split] = distinct_cameras([f.camera for f in scene.frames], seen)
    except DatasetError as err:
        return DatasetCameras(cameras, background, f"{err} (its cameras are not shown)")
    return DatasetCameras(cameras, background, "")


def distinct_cameras(cameras: list[Camera], seen: set, decimals: int = 4) -> list[Camera]:
    """``cameras`` without repeats (a camera filmed at many times appears once) nor the poses in
    ``seen``, in order; adds the poses kept to ``seen``."""
    kept = []
    for cam in cameras:
        key = tuple(np.round(cam.viewmat.cpu().numpy(), decimals).ravel()) + (cam.width, cam.height)
        if key not in seen:
            seen.add(key)
            kept.append(cam)
    return kept
