"""``tracegs segment``: group a trained run's Gaussians by their learned motion, store the labels in the
run folder, render the masks at any time, and score them where the scene has ground truth.

Writes ``RUN/segments.pt`` (``segments-flow.pt`` for the flow baseline: ``labels`` [N], ``k``,
``has_static``, the settings) and, under ``--out`` (default ``RUN/segment``, ``RUN/segment-flow``):
``segment.json``, ``masks_t<T>.png`` (per camera: the image with the segments over it, the predicted
mask, the ground truth's), ``segments_t<T>.ply`` (the Gaussians at T in their segment's colour) and,
with ``video``, ``sweep.mp4``.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch

from ..data.cameras import scene_extent_from_cameras
from ..data.scene import available_splits, load_scene
from ..export.ply import write_gaussians
from ..export.render import sweep, write_video
from ..extrapolate import Predictor
from ..models.gaussians import rgb_to_sh0
from ..run import load_run, load_tensors, run_data, save_tensors
from ..utils import atomic_write_image, atomic_write_text
from .cluster import Segmentation, segment
from .config import SegmentConfig
from .features import motion_features
from .masks import colour_image, colours, overlay
from .score import score_segmentation
from .truth import GroundTruth, find_ground_truth


def labels_file(run: Path, features: str) -> Path:
    return Path(run) / ("segments.pt" if features == "physics" else f"segments-{features}.pt")


def segment_run(
    run: str | Path,
    data: str | Path | None = None,
    k: int | None = None,
    auto_k: bool = False,
    time_: float | None = None,
    json_path: str | Path | None = None,
    out: str | Path | None = None,
    video: bool = False,
    settings: SegmentConfig | None = None,
    score: bool = True,
    device: str = "auto",
    ignore_pixels: int = 0,
) -> dict:
    """Segment the run ``run`` into ``k`` segments (the static group counted) or, with ``auto_k``, the K
    of ``cluster.choose_k``; write the outputs (module docstring) and return the report that goes to
    ``segment.json`` (and to ``json_path``). ``ignore_pixels``: ground-truth segments smaller than
    this are left out of the scores (OGC's rule; 0, the default, scores every one)."""
    settings = settings or SegmentConfig()
    if (k is None) == (not auto_k):
        raise ValueError("give K (--k K) or ask for --auto-k, not both" if k else "give --k K or --auto-k")
    started = time.perf_counter()
    loaded = load_run(run, device, data)
    predictor, cfg = loaded.predictor, loaded.config
    data = run_data(cfg, data)  # (a clear error when the scene is not there)
    train = load_scene(data, "train", cfg.downscale)
    extent = scene_extent_from_cameras(torch.stack([f.camera.center for f in train.frames]))
    features = motion_features(predictor, settings, extent)
    seg = segment(features, settings, None if auto_k else k)
    seconds_segment = time.perf_counter() - started
    run = Path(run)
    save_tensors(
        {"labels": torch.as_tensor(seg.labels), "k": seg.k, "has_static": seg.has_static,
         "time": features.time, "settings": asdict(settings)},
        labels_file(run, settings.features),
    )  # fmt: skip
    report = {
        "run": str(run),
        "features": settings.features,
        "k": seg.k,
        "auto_k": {"criterion": "rigid residual", "tolerance": settings.rigid_tolerance, "tried": seg.auto_k}
        if auto_k
        else None,
        "time": features.time,
        "static_threshold": features.static_threshold,
        "segments": _segments(seg),
        "free_bodies": agreement_with_free_bodies(predictor.state, seg.labels),
        "settings": asdict(settings),
        "seconds": {"segment": seconds_segment},
    }
    if k is not None and seg.k != k:
        report["note"] = (
            f"asked for K = {k}, made {seg.k}: {int((~features.static).sum())} Gaussians move more than "
            f"{features.static_threshold:g} over the training span"
        )
    out = Path(out or run / ("segment" if settings.features == "physics" else f"segment-{settings.features}"))
    labels = torch.as_tensor(seg.labels)
    truth = find_ground_truth(data)
    t_show = features.time if time_ is None else float(time_)
    report["outputs"] = write_outputs(predictor, seg, labels, data, cfg.downscale, truth, t_show, out)
    if video:
        report["outputs"]["video"] = str(segment_video(predictor, seg, labels, data, cfg.downscale, out))
    if truth is not None and score:
        started = time.perf_counter()
        report["ground_truth"] = {
            "layout": truth.layout,
            "merged": truth.merged,
            "note": _truth_note(truth),
        }
        report["scores"] = score_segmentation(
            predictor, labels, seg.k, seg.has_static, data, cfg.downscale, truth,
            ignore_pixels=ignore_pixels,
        )  # fmt: skip
        report["seconds"]["score"] = time.perf_counter() - started
    text = json.dumps(report, indent=2)
    atomic_write_text(out / "segment.json", text)
    if json_path is not None:
        atomic_write_text(Path(json_path), text)
    return report


def load_segments(run: str | Path, features: str = "physics") -> dict:
    """The labels stored by :func:`segment_run` (``labels`` [N] long, ``k``, ``has_static``, ...)."""
    path = labels_file(Path(run), features)
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no segmentation; make it with `tracegs segment --run {run} --auto-k`"
        )
    return load_tensors(path)


def _segments(seg: Segmentation) -> list[dict]:
    counts = np.bincount(seg.labels, minlength=seg.k)
    return [
        {"label": i, "gaussians": int(counts[i]), "static": bool(seg.has_static and i == 0)}
        for i in range(seg.k)
    ]


def _truth_note(truth: GroundTruth) -> str:
    if truth.layout == "foreground":
        return (
            "foreground / background only (the scene's seg/ masks): the moving segments against the static "
            "group and the background; not the paper's per-object protocol"
        )
    merged = "; ".join(", ".join(group) for group in truth.merged)
    return "every part is a segment" + (f", but parts moving alike are one: {merged}" if merged else "")


def agreement_with_free_bodies(state, labels: np.ndarray) -> list[dict]:
    """For each free body the extrapolation policy chose: the segment holding most of its Gaussians, the
    share of the body in it (purity) and the share of that segment in the body (coverage)."""
    bodies = state.free_bodies
    if bodies is None or not len(bodies["bodies"]):
        return []
    body_of = bodies["labels"].cpu().numpy()
    if len(body_of) != len(labels):
        return []
    rows = []
    for b in range(1, int(body_of.max()) + 1):
        members = labels[body_of == b]
        if not len(members):
            continue
        main = int(np.bincount(members).argmax())
        inside = int((members == main).sum())
        rows.append(
            {"body": b, "gaussians": len(members), "segment": main, "purity": inside / len(members),
             "coverage": inside / int((labels == main).sum())}
        )  # fmt: skip
    return rows


@torch.no_grad()
def coloured_gaussians(model, gaussians: dict, labels: torch.Tensor, palette: np.ndarray) -> dict:
    """The Gaussians at some time with their segment's colour as the only (view-independent) colour."""
    g = model.gaussians
    dev = g["means"].device
    rgb = torch.as_tensor(palette, dtype=torch.float32, device=dev)[labels.to(dev).long()]
    return {
        "means": gaussians["means"], "quats": gaussians["quats"], "scales": gaussians["scales"],
        "opacities": g["opacities"], "sh0": rgb_to_sh0(rgb)[:, None, :],
        "shN": torch.zeros(len(rgb), 0, 3, device=dev),
    }  # fmt: skip


def _cameras_at(data: Path, downscale: int, t: float, truth: GroundTruth | None, count: int = 3) -> list:
    """Up to ``count`` frames at time ``t`` (with a ground-truth mask when there is one), else the first
    training cameras (frames at another time)."""
    found = []
    for split in available_splits(data):
        for frame in load_scene(data, split, downscale).frames:
            if abs(frame.time - t) < 1e-6 and (truth is None or truth.mask_path(frame).is_file()):
                found.append(frame)
    if not found:
        found = load_scene(data, "train", downscale).frames
    step = max(1, len(found) // count)
    return found[::step][:count]


def write_outputs(predictor: Predictor, seg, labels, data, downscale, truth, t, out: Path) -> dict:
    """The mask strip and the coloured PLY at time ``t``."""
    palette = colours(seg.k, seg.has_static)
    gaussians = predictor.gaussians_at(t)
    rows = []
    for frame in _cameras_at(data, downscale, t, truth):
        cam = frame.camera.to(predictor.device)
        image = predictor.render(cam, gaussians=gaussians).cpu().numpy()
        pred, _ = predictor.render_labels(cam, labels, seg.k, gaussians=gaussians)
        row = [overlay(image, pred, palette), colour_image(pred, palette)]
        gt = truth.read(frame) if truth is not None and abs(frame.time - t) < 1e-6 else None
        if gt is not None:
            ids = np.unique(gt)
            grey = np.linspace(0.25, 0.85, max(len(ids) - 1, 1))
            gt_colour = np.ones(gt.shape + (3,))
            for value, shade in zip(ids[ids > 0], grey, strict=False):
                gt_colour[gt == value] = shade
            row.append(gt_colour)
        rows.append(np.concatenate(row, axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=1.0) for r in rows]
    strip = atomic_write_image(out / f"masks_t{t:.3f}.png", np.concatenate(rows, axis=0))
    ply = write_gaussians(
        coloured_gaussians(predictor.model, gaussians, labels, palette), out / f"segments_t{t:.3f}.ply"
    )
    return {"masks": str(strip), "ply": str(ply)}


def segment_video(
    predictor: Predictor, seg, labels, data, downscale, out: Path, t_end=1.5, frames=90
) -> Path:
    """An orbit while time runs 0 -> ``t_end``, the segments painted over the rendered images."""
    palette = colours(seg.k, seg.has_static)

    def paint(image, gaussians, cam):
        pred, _ = predictor.render_labels(cam, labels, seg.k, gaussians=gaussians)
        return overlay(image, pred, palette)

    return write_video(sweep(predictor, data, t_end, frames, downscale, paint), out / "sweep.mp4")
