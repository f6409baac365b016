"""``synthesize``: render a synthetic scene into a Blender / D-NeRF style folder with ground truth.

Output layout (all paths relative to ``out``)::

    transforms_{train,val,test}.json   cameras, times and image paths per split
    {train,val,test}/cXX_fYYY.png      RGBA, 8-bit sRGB, straight alpha, transparent background
    gt/masks/{split}/cXX_fYYY.png      uint8 part id per pixel (0 = background)
    gt/motion.json                     closed-form motion parameters of every part (any motion type)
    gt/part_transforms.npz             times [F], transforms [F, P, 4, 4] (rest -> world)
    gt/points.npz                      points [M, 3] on the rest-pose surface, part_ids [M]
    gt/synth.json                      the settings the folder was made with

The folder is assembled under a temporary name next to ``out`` and renamed into place at the end, so
an interrupted run never leaves a half-written dataset under the final name.

# C: cameras, F: frames, P: parts, M: points
"""

from __future__ import annotations

import json
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from ...utils import fresh_folder, replace_folder
from . import geometry as g
from .cameras import Rig, Split, default_train_frames, default_val_views, make_rig, make_split
from .motion import EQUATIONS, FORMULA, motion_record, transforms_at
from .render import (
    Lighting,
    build_scene,
    make_sensors,
    pose,
    render_part_ids,
    render_rgba,
    samples_per_pixel,
    to_srgb8,
)
from .room import room_pieces
from .scenes import SceneSpec, get_scene

EXTRAPOLATION_HORIZON = 1.5
"""Bounds and camera framing cover the object for all t in [0, EXTRAPOLATION_HORIZON]."""
DEFAULT_SPP = 16
"""Samples per pixel of the colour images (a 4 x 4 stratified grid): about 43 dB from the converged image."""
POINTS = 12_000
"""Target size of the ground-truth surface point cloud."""
MIN_POINTS_PER_PART = 600


@dataclass(frozen=True)
class Bounds:
    aabb: np.ndarray  # [2, 3] min / max corner over t in [0, EXTRAPOLATION_HORIZON]
    center: np.ndarray  # [3] centre of the box, where the cameras look
    radius: float  # largest distance of a surface vertex from the centre


def motion_bounds(spec: SceneSpec, horizon: float = EXTRAPOLATION_HORIZON, steps: int = 151) -> Bounds:
    """Bounds of every vertex of every part, sampled densely over t in [0, horizon]."""
    times = np.linspace(0.0, horizon, steps)
    transforms = transforms_at([p.motion for p in spec.parts], times)  # [T, P, 4, 4]
    world = []
    for i in range(len(spec.parts)):
        v = spec.part_mesh(i).vertices.astype(np.float64)
        m = transforms[:, i]
        world.append((np.einsum("tij,vj->tvi", m[:, :3, :3], v) + m[:, None, :3, 3]).reshape(-1, 3))
    world = np.concatenate(world)
    aabb = np.stack([world.min(0), world.max(0)])
    center = aabb.mean(0)
    return Bounds(aabb, center, float(np.linalg.norm(world - center, axis=1).max()))


def sample_rest_points(spec: SceneSpec, seed: int, total: int = POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted surface samples of the rest pose: points [M, 3] float32, part ids [M] uint8
    (each part gets its share of ``total`` by area, and at least MIN_POINTS_PER_PART)."""
    rng = np.random.default_rng([seed, 7])
    meshes = [spec.part_mesh(i) for i in range(len(spec.parts))]
    areas = np.array([g.surface_area(m) for m in meshes])
    counts = np.maximum(MIN_POINTS_PER_PART, np.round(total * areas / areas.sum()).astype(int))
    points = [g.sample_surface(m, int(n), rng) for m, n in zip(meshes, counts, strict=True)]
    ids = [np.full(int(n), i + 1, dtype=np.uint8) for i, n in enumerate(counts)]
    return np.concatenate(points).astype(np.float32), np.concatenate(ids)


def image_name(camera: int, frame: int, views: int, frames: int) -> str:
    cw, fw = max(2, len(str(views - 1))), max(3, len(str(frames - 1)))
    return f"c{camera:0{cw}d}_f{frame:0{fw}d}.png"


def transforms_json(
    scene: str,
    split: str,
    pairs: list[tuple[int, int]],
    rig: Rig,
    times: np.ndarray,
    resolution: int,
    t_train_end: float,
    aabb: np.ndarray,
) -> dict:
    """One ``transforms_{split}.json`` in Blender / D-NeRF conventions plus the synthetic extras."""
    views, frames = len(rig.c2w), len(times)
    return {
        "scene": scene,
        "camera_angle_x": rig.camera_angle_x,
        "w": resolution,
        "h": resolution,
        "fps": frames - 1,
        "t_train_end": t_train_end,
        "background": [1.0, 1.0, 1.0],
        "aabb": aabb.tolist(),
        "frames": [
            {
                "file_path": f"{split}/{image_name(c, f, views, frames)}",
                "time": float(times[f]),
                "camera_id": c,
                "frame_id": f,
                "transform_matrix": rig.c2w[c].tolist(),
            }
            for c, f in pairs
        ],
    }


def _validate(scene, resolution, views, frames, train_views, train_frames, spp, seed) -> SceneSpec:
    spec = get_scene(scene)
    checks = [
        (resolution >= 8, f"resolution must be >= 8 pixels, got {resolution}"),
        (views >= 2, f"views must be >= 2 (train and held-out cameras), got {views}"),
        (frames >= 2, f"frames must be >= 2 (train and extrapolation frames), got {frames}"),
        (spp >= 1, f"spp must be >= 1, got {spp}"),
        (seed >= 0, f"seed must be >= 0, got {seed}"),
        (
            train_views is None or 1 <= train_views < views,
            f"train_views must be in [1, views - 1] = [1, {views - 1}], got {train_views}",
        ),
        (
            train_frames is None or 1 <= train_frames < frames,
            f"train_frames must be in [1, frames - 1] = [1, {frames - 1}], got {train_frames}",
        ),
    ]
    for ok, message in checks:
        if not ok:
            raise ValueError(message)
    return spec


def _write_json(path: Path, data: dict) -> None:
    path.write_text(json.dumps(data, indent=2) + "\n")


def _progress(total: int, enabled: bool, desc: str):
    if not enabled:
        return None
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit="img")


def synthesize(
    scene: str,
    out: str | Path,
    resolution: int = 128,
    views: int = 15,
    frames: int = 60,
    seed: int = 0,
    train_views: int | None = None,
    train_frames: int | None = None,
    progress: bool = True,
    *,
    spp: int = DEFAULT_SPP,
    sun: float = Lighting.sun_irradiance,
    ambient: float = Lighting.ambient,
    textured_surroundings: bool = False,
) -> Path:
    """Render ``scene`` (one of ``SCENES``) with ground truth into the folder ``out``; returns it.

    ``views`` cameras x ``frames`` frames at times t_k = k / (frames - 1). Train: the first
    ``train_frames`` frames (default round(46/60 * frames)) of the first ``train_views`` cameras
    (default views - max(1, round(0.2 * views))); val: the same frames of the other cameras; test:
    the remaining frames of every camera. The same arguments give byte-identical images.
    ``sun`` and ``ambient`` set the light (``render.Lighting``): ``sun=0`` gives a scene whose surfaces
    look the same whichever way they face (no shading, no shadows), for telling motion errors from
    the shading changes that no motion of constant-colour Gaussians renders.
    ``textured_surroundings``: a textured floor and walls round the scene (``room.py``), which a
    calibration matches between the cameras; the images are opaque then.
    """
    spec = _validate(scene, resolution, views, frames, train_views, train_frames, spp, seed)
    if not (sun >= 0 and ambient >= 0 and sun + ambient > 0):
        raise ValueError(f"sun and ambient must be >= 0 and not both 0, got sun={sun}, ambient={ambient}")
    lighting = Lighting(ambient=float(ambient), sun_irradiance=float(sun))
    out = Path(out)
    n_train_views = views - default_val_views(views) if train_views is None else train_views
    n_train_frames = default_train_frames(frames) if train_frames is None else train_frames
    times = np.arange(frames) / (frames - 1)
    motions = [p.motion for p in spec.parts]
    bounds = motion_bounds(spec)
    rig = make_rig(views, n_train_views, bounds.center, bounds.radius, seed)
    split: Split = make_split(views, frames, n_train_views, n_train_frames)
    split_of = {pair: name for name, pairs in split.items() for pair in pairs}

    tmp = fresh_folder(out, "tracegs synth", "gt/synth.json")
    try:
        for name in ("train", "val", "test"):
            (tmp / name).mkdir()
            (tmp / "gt" / "masks" / name).mkdir(parents=True)
        started = time.perf_counter()
        room = ()
        if textured_surroundings:
            distance = float(np.linalg.norm(rig.c2w[0, :3, 3] - bounds.center))
            room = room_pieces(bounds.aabb, bounds.center, distance, seed)
        ms = build_scene(spec, lighting, room)
        sensors = [make_sensors(c2w, rig.camera_angle_x, resolution, spp) for c2w in rig.c2w]
        bar = _progress(views * frames, progress, f"synth {scene}")
        for f, t in enumerate(times):
            pose(ms, transforms_at(motions, t))
            for c, (color_sensor, mask_sensor) in enumerate(sensors):
                rel = f"{split_of[(c, f)]}/{image_name(c, f, views, frames)}"
                # One seed per image: independent noise, reproducible from (seed, camera, frame).
                rgba = render_rgba(ms, color_sensor, seed=((seed * frames + f) * views + c) % 2**32)
                iio.imwrite(tmp / rel, to_srgb8(rgba))
                iio.imwrite(tmp / "gt" / "masks" / rel, render_part_ids(ms, mask_sensor))
                if bar is not None:
                    bar.update(1)
        if bar is not None:
            bar.close()
        render_seconds = time.perf_counter() - started

        t_train_end = float(times[n_train_frames - 1])
        for name, pairs in split.items():
            data = transforms_json(scene, name, pairs, rig, times, resolution, t_train_end, bounds.aabb)
            _write_json(tmp / f"transforms_{name}.json", data)
        _write_gt(tmp / "gt", spec, times, seed)
        settings = {
            "scene": scene,
            "resolution": resolution,
            "views": views,
            "frames": frames,
            "seed": seed,
            "train_views": n_train_views,
            "train_frames": n_train_frames,
            "spp": samples_per_pixel(spp),
            "sun": lighting.sun_irradiance,
            "ambient": lighting.ambient,
            "render_seconds": round(render_seconds, 2),
        } | ({"textured_surroundings": True} if textured_surroundings else {})
        _write_json(tmp / "gt" / "synth.json", settings)
        replace_folder(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def _formulas(records: list[dict]) -> dict:
    """Closed form of each motion type of ``records`` (nested ones included) other than ``FORMULA``'s."""
    found = {}
    for record in records:
        nested = [record.get(key) for key in ("parent", "child")]
        found |= _formulas([r for r in nested if r is not None])
        if record["type"] in EQUATIONS:
            found[record["type"]] = EQUATIONS[record["type"]]
    return found


def _write_gt(gt: Path, spec: SceneSpec, times: np.ndarray, seed: int) -> None:
    motions = [p.motion for p in spec.parts]
    parts = [motion_record(p.name, i + 1, p.motion) for i, p in enumerate(spec.parts)]
    others = _formulas(parts)
    _write_json(
        gt / "motion.json",
        {
            "scene": spec.name,
            "description": spec.description,
            "formula": FORMULA,
            **({"formulas": others} if others else {}),
            "time": "t_k = k / (frames - 1); fps = frames - 1 frames per unit of t",
            "units": "scene units and radians per unit of t; axis and pivot in world coordinates at t = 0",
            "parts": parts,
        },
    )
    np.savez_compressed(
        gt / "part_transforms.npz",
        times=times,
        transforms=transforms_at(motions, times),
        part_ids=np.arange(1, len(motions) + 1),
        part_names=np.array([p.name for p in spec.parts]),
    )
    points, ids = sample_rest_points(spec, seed)
    np.savez_compressed(gt / "points.npz", points=points, part_ids=ids)
