"""Calibrating a static rig with COLMAP (``pycolmap``, on the CPU), and undistorting its images.

``calibrate_rig`` runs COLMAP's pipeline on a few frames of each camera taken while the rig stood
still: SIFT features (affine-adapted and domain-size pooled, which match across the wide baselines of a
rig of few cameras), exhaustive matching with guided geometric verification, incremental mapping.
Every camera's frames share one COLMAP camera (its folder is its camera), so ``--calib-frames N`` adds
views of a scene with little texture without adding unknowns. The mapper's thresholds are lowered
from COLMAP's defaults (made for photo collections of thousands of features) to what a rig of a few
small views gives: 30 inliers start a model, 12 register a camera. The focal lengths and distortion
are held at COLMAP's prior while the model grows, then refined by bundle adjustments of every camera
together (a robust loss; the observations left more than 2 pixels off dropped between rounds). A
camera none of whose frames is registered, or that lies in another model than the largest, is
unregistered and named with what COLMAP had for it.

Undistortion (``undistortion_map``, ``undistort``): the output camera is the pinhole part of the
model (its focal lengths and principal point, the same size); each of its pixels takes the colour
of the distorted image where the model projects the pixel's ray (bilinear), black outside it.

C: cameras, N: points, H, W: image size
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .frames import DatasetError

PINHOLE_MODELS = ("SIMPLE_PINHOLE", "PINHOLE")
CAMERA_MODELS = ("SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV")
"""The models ``--camera-model`` takes (COLMAP's names); the last three have radial distortion."""


@dataclass
class CameraFit:
    """One calibrated camera: OpenCV world-to-camera, pinhole intrinsics of the undistorted image, and
    the COLMAP camera the images were taken with (None when it has no distortion)."""

    w2c: np.ndarray  # [4, 4]
    K: np.ndarray  # [3, 3]
    width: int
    height: int
    distorted: object | None = None  # pycolmap.Camera of the recorded images


@dataclass
class RigFit:
    """What a calibration gives: the cameras it placed and, for the report, the rest."""

    cameras: dict[str, CameraFit]
    unregistered: dict[str, str] = field(default_factory=dict)  # camera name -> why
    report: dict = field(default_factory=dict)
    points: np.ndarray | None = None  # [N, 3] the sparse points, world coordinates of ``cameras``


def pinhole_fit(camera, w2c: np.ndarray) -> CameraFit:
    """A ``CameraFit`` from a ``pycolmap.Camera`` and its world-to-camera [4, 4]."""
    K = np.asarray(camera.calibration_matrix(), dtype=np.float64)
    model = camera.model_name if hasattr(camera, "model_name") else camera.model.name
    return CameraFit(
        w2c, K, int(camera.width), int(camera.height), None if model in PINHOLE_MODELS else camera
    )


def _w2c(image) -> np.ndarray:
    w2c = np.eye(4)
    w2c[:3] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
    return w2c


def calibrate_rig(
    image_root: Path,
    names: dict[str, list[str]],
    work: Path,
    camera_model: str = "SIMPLE_RADIAL",
    seed: int = 0,
) -> RigFit:
    """Calibrate the cameras ``names`` (camera -> its calibration images, paths under ``image_root`` in
    a folder of the camera's own) with COLMAP; ``work`` holds the database and the models."""
    import pycolmap

    if camera_model not in CAMERA_MODELS:
        raise ValueError(f"--camera-model {camera_model!r}: choose from {', '.join(CAMERA_MODELS)}")
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # COLMAP's errors only: the report says what it did
    try:
        return _calibrate(pycolmap, image_root, names, work, camera_model, seed)
    finally:
        pycolmap.logging.minloglevel = level


FOCAL_PASSES = 4
"""Most mappings of a rig, each from the focal lengths the one before refined (``_focal_priors``)."""
FOCAL_SETTLED = 0.02
"""Median relative change of the refined focal lengths below which they have settled."""


def _calibrate(
    pycolmap, image_root: Path, names: dict[str, list[str]], work: Path, camera_model: str, seed: int
):
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    if database.exists():
        database.unlink()
    pycolmap.set_random_seed(seed)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = camera_model
    image_names = [n for camera in names.values() for n in camera]
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.estimate_affine_shape = True
    extraction.sift.domain_size_pooling = True
    extraction.num_threads = 2
    pycolmap.extract_features(
        database,
        image_root,
        image_names=image_names,
        camera_mode=pycolmap.CameraMode.PER_FOLDER,
        reader_options=reader,
        extraction_options=extraction,
        device=pycolmap.Device.cpu,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.guided_matching = True
    matching.num_threads = 2
    pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    counts = _database_counts(database, names)
    options = pycolmap.IncrementalPipelineOptions()
    options.min_model_size = 2
    options.min_num_matches = 10
    options.mapper.init_min_num_inliers = 30
    options.mapper.abs_pose_min_num_inliers = 12
    options.random_seed = seed
    # the focal lengths stay at COLMAP's prior (1.2 x the larger side) while the rig is assembled: with
    # a few hundred points, a focal length per camera refined from the first views drifts (the
    # focal-depth ambiguity) and the rig folds; the final bundle adjustment refines them all at once
    options.ba_refine_focal_length = options.ba_refine_extra_params = False
    options.mapper.abs_pose_refine_focal_length = options.mapper.abs_pose_refine_extra_params = False
    options.num_threads = 2
    sparse = work / "sparse"
    focals = []
    for _ in range(FOCAL_PASSES):  # mapped again from the refined focal lengths until they settle
        shutil.rmtree(sparse, ignore_errors=True)
        sparse.mkdir()
        models = pycolmap.incremental_mapping(database, image_root, sparse, options=options)
        if not models:
            raise DatasetError(f"{image_root}: COLMAP made no model of the cameras ({_counts_text(counts)})")
        best_id, best = max(models.items(), key=lambda kv: kv[1].num_reg_images())
        _refine(best)
        change, focal = _focal_priors(pycolmap, database, best)
        focals.append(focal)
        if change < FOCAL_SETTLED:
            break
    best.write(sparse / str(best_id))  # the folder a later `--calibration` takes
    fit = _rig_fit(best, names, counts, models, sparse / str(best_id))
    fit.report["focal_passes"] = [round(f, 2) for f in focals]
    return fit


def _focal_priors(pycolmap, database: Path, model) -> tuple[float, float]:
    """Set the database's focal-length priors to those the bundle adjustment of ``model`` refined;
    returns the median relative change and the median refined focal length. The mapping holds the
    priors while it assembles the rig (see ``_calibrate``), so a prior far from the truth (COLMAP's
    1.2 x the larger side, against a wide lens's 0.7) folds the rig: mapping again from the refined
    ones, until they settle, undoes it."""
    db = pycolmap.Database.open(str(database))
    changes, refined = [], []
    try:
        for camera in db.read_all_cameras():
            if camera.camera_id not in model.cameras:
                continue
            new = model.cameras[camera.camera_id]
            params = np.asarray(camera.params, dtype=np.float64).copy()
            for i in camera.focal_length_idxs():
                changes.append(abs(new.params[i] / params[i] - 1.0))
                refined.append(float(new.params[i]))
                params[i] = new.params[i]
            camera.params = params
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()
    return (float(np.median(changes)) if changes else 0.0), (float(np.median(refined)) if refined else 0.0)


def _refine(model, rounds: int = 3) -> None:
    """Bundle adjustment of every camera, its intrinsics included (robust loss), and the observations
    it leaves more than 2 pixels off dropped, ``rounds`` times."""
    import pycolmap

    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    for _ in range(rounds):
        pycolmap.bundle_adjustment(model, options)
        if pycolmap.ObservationManager(model).filter_all_points3D(2.0, 1.5) == 0:
            break
    options.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    pycolmap.bundle_adjustment(model, options)


def _database_counts(database: Path, names: dict[str, list[str]]) -> dict[str, dict]:
    """Per camera: SIFT features and the verified matches with every other camera (summed)."""
    import pycolmap

    db = pycolmap.Database.open(str(database))
    try:
        camera_of = {}
        counts = {c: {"features": 0, "verified_matches": 0} for c in names}
        for image in db.read_all_images():
            camera = image.name.split("/")[0]
            camera_of[image.image_id] = camera
            if camera in counts:
                counts[camera]["features"] += db.num_keypoints_for_image(image.image_id)
        pair_ids, inliers = db.read_two_view_geometry_num_inliers()
        for pair_id, n in zip(pair_ids, inliers, strict=True):
            a, b = (camera_of.get(i) for i in pycolmap.pair_id_to_image_pair(pair_id))
            for camera in {a, b} - {None}:
                if a != b:
                    counts[camera]["verified_matches"] += int(n)
    finally:
        db.close()
    return counts


def _counts_text(counts: dict[str, dict]) -> str:
    return "; ".join(
        f"{c}: {v['features']} features, {v['verified_matches']} verified matches" for c, v in counts.items()
    )


def _rig_fit(best, names: dict[str, list[str]], counts: dict, models: dict, path: Path) -> RigFit:
    by_camera: dict[str, list] = {}
    for image in best.images.values():
        if image.has_pose:
            by_camera.setdefault(image.name.split("/")[0], []).append(image)
    others = {
        image.name.split("/")[0] for m in models.values() if m is not best for image in m.images.values()
    }
    cameras, unregistered, spread = {}, {}, {}
    for name in names:
        images = sorted(by_camera.get(name, []), key=lambda im: im.name)
        if not images:
            why = (
                "in a separate COLMAP model: no matches tie it to the others"
                if name in others
                else "not registered"
            )
            c = counts.get(name, {})
            unregistered[name] = (
                f"{why} ({c.get('features', 0)} features, {c.get('verified_matches', 0)} verified matches)"
            )
            continue
        cameras[name] = pinhole_fit(best.cameras[images[0].camera_id], _w2c(images[0]))
        centres = np.array([image.projection_center() for image in images])
        spread[name] = float(np.linalg.norm(centres - centres[0], axis=1).max())
    points = np.array([p.xyz for p in best.points3D.values()], dtype=np.float64).reshape(-1, 3)
    report = {
        "tool": "COLMAP (pycolmap)",
        "model": str(path),
        "registered_images": best.num_reg_images(),
        "points": len(points),
        "mean_reprojection_error_px": float(best.compute_mean_reprojection_error()),
        "per_camera": {c: counts[c] | {"registered": c in cameras} for c in names},
        "pose_spread_colmap_units": spread,
    }
    return RigFit(cameras, unregistered, report, points)


def undistortion_map(camera, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """[2, H, W] (row, column) in the image of the distorted ``camera`` (pycolmap) where each pixel of
    the pinhole camera ``K`` [3, 3] of ``width`` x ``height`` looks (pixel centres at + 0.5)."""
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
    xy = np.asarray(camera.img_from_cam(rays, check_cheirality=False), dtype=np.float64).reshape(
        height, width, 2
    )
    return np.stack([xy[..., 1] - 0.5, xy[..., 0] - 0.5])


def largest_shift(coords: np.ndarray) -> float:
    """The largest distance in pixels between a pixel and where the map ``coords`` [2, H, W] takes it."""
    H, W = coords.shape[1:]
    rows, cols = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    return float(np.hypot(coords[0] - rows, coords[1] - cols).max())


def undistort(image: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """[H, W, 3] ``image`` resampled at ``coords`` [2, H', W'] (bilinear, black outside) -> [H', W', 3]."""
    from scipy import ndimage

    channels = [
        ndimage.map_coordinates(image[..., k].astype(np.float32), coords, order=1, mode="constant", cval=0.0)
        for k in range(image.shape[-1])
    ]
    out = np.stack(channels, -1)
    return np.clip(np.round(out), 0, 255).astype(image.dtype) if image.dtype == np.uint8 else out
