"""A rig's calibration from a file (``tracegs import --calibration``), and the similarity transforms
that place a calibration in the scene: round the origin, up along +z, at a chosen size
(``normalise``), or onto another calibration of the same rig (``umeyama``, ``align_cameras``).

``read_calibration`` takes a COLMAP model folder (``cameras``, ``images``, ``points3D`` as .bin or
.txt), a nerfstudio ``transforms.json`` (OpenGL camera-to-world ``transform_matrix`` per frame,
``fl_x``/``fl_y``/``cx``/``cy``/``w``/``h`` per frame or for the file, OpenCV distortion ``k1``, ``k2``,
``p1``, ``p2``) or a Dynamic 3D Gaussians ``*_meta.json`` (``k``, ``w2c``, ``fn``, ``cam_id`` of the first
frame; a folder of them reads them all). A camera of the rig is found there by name: the folder or
the file stem of a COLMAP image name or a nerfstudio ``file_path``, the folder of a Dynamic 3D
Gaussians ``fn`` or its ``cam_id``.

C: cameras
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .colmap import CameraFit, RigFit, pinhole_fit
from .frames import DatasetError, load_json


def _names_of(path: str) -> set[str]:
    p = Path(path)
    return {p.stem, p.parent.name} - {""}


def _pick(path: Path, found: dict[str, CameraFit], wanted: list[str]) -> RigFit:
    """The cameras ``wanted`` among those of the file (``found``: name -> fit); the missing ones are
    unregistered."""
    cameras = {n: found[n] for n in wanted if n in found}
    missing = {n: f"not in {path}" for n in wanted if n not in found}
    return RigFit(cameras, missing, {"tool": "given", "file": str(path)})


def read_colmap_model(path: Path, wanted: list[str]) -> RigFit:
    import pycolmap

    try:
        model = pycolmap.Reconstruction(str(path))
    except Exception as e:
        raise DatasetError(f"{path}: not a COLMAP model ({' '.join(str(e).split())})") from None
    found: dict[str, CameraFit] = {}
    for image in sorted(model.images.values(), key=lambda im: im.name):
        if not image.has_pose:
            continue
        w2c = np.eye(4)
        w2c[:3] = np.asarray(image.cam_from_world().matrix())
        fit = pinhole_fit(model.cameras[image.camera_id], w2c)
        for name in _names_of(image.name):
            found.setdefault(name, fit)
    fit = _pick(path, found, wanted)
    fit.report |= {
        "tool": "COLMAP model",
        "mean_reprojection_error_px": float(model.compute_mean_reprojection_error()),
    }
    fit.points = np.array([p.xyz for p in model.points3D.values()], dtype=np.float64).reshape(-1, 3)
    return fit


def _opencv_camera(fx, fy, cx, cy, width, height, dist):
    import pycolmap

    return pycolmap.Camera(model="OPENCV", width=width, height=height, params=[fx, fy, cx, cy, *dist])


def read_nerfstudio(path: Path, wanted: list[str]) -> RigFit:
    data = load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise DatasetError(f"{path}: a nerfstudio transforms.json has a list 'frames'")
    found: dict[str, CameraFit] = {}
    for i, frame in enumerate(data["frames"]):
        get = lambda k, frame=frame: frame.get(k, data.get(k))  # noqa: E731
        try:
            c2w = np.asarray(frame["transform_matrix"], dtype=np.float64)
            fx, fy, cx, cy = (float(get(k)) for k in ("fl_x", "fl_y", "cx", "cy"))
            width, height = int(get("w")), int(get("h"))
            dist = [float(get(k) or 0.0) for k in ("k1", "k2", "p1", "p2")]
        except (KeyError, TypeError, ValueError):
            raise DatasetError(
                f"{path}: frame {i} needs 'transform_matrix', 'file_path' and fl_x, fl_y, cx, cy, w, h"
            ) from None
        if c2w.shape != (4, 4) or not np.isfinite(c2w).all():
            raise DatasetError(f"{path}: frame {i}: 'transform_matrix' must be a finite 4x4 matrix")
        c2w[:3, 1:3] *= -1  # OpenGL -> OpenCV camera axes
        K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        distorted = _opencv_camera(fx, fy, cx, cy, width, height, dist) if any(dist) else None
        fit = CameraFit(np.linalg.inv(c2w), K, width, height, distorted)
        for name in _names_of(str(frame.get("file_path", ""))):
            found.setdefault(name, fit)
    return _pick(path, found, wanted)


def read_dynamic3dgs(paths: list[Path], wanted: list[str]) -> RigFit:
    found: dict[str, CameraFit] = {}
    for path in paths:
        meta = load_json(path)
        try:
            width, height = int(meta["w"]), int(meta["h"])
            k, w2c, fn, ids = (meta[key][0] for key in ("k", "w2c", "fn", "cam_id"))
            for K, m, name, cam_id in zip(k, w2c, fn, ids, strict=True):
                fit = CameraFit(
                    np.asarray(m, dtype=np.float64), np.asarray(K, dtype=np.float64), width, height
                )
                for n in (Path(name).parent.name, str(cam_id)):
                    found.setdefault(n, fit)
        except (KeyError, TypeError, ValueError, IndexError):
            raise DatasetError(
                f"{path}: a Dynamic 3D Gaussians meta has w, h and per frame k, w2c, fn, cam_id"
            ) from None
    return _pick(paths[0] if len(paths) == 1 else paths[0].parent, found, wanted)


def read_calibration(path: Path, wanted: list[str]) -> RigFit:
    """The cameras ``wanted`` (names) of the calibration at ``path`` (module docstring)."""
    path = Path(path)
    if path.is_dir():
        if any((path / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return read_colmap_model(path, wanted)
        metas = sorted(path.glob("*_meta.json"))
        if metas:
            return read_dynamic3dgs(metas, wanted)
        if (path / "transforms.json").is_file():
            return read_nerfstudio(path / "transforms.json", wanted)
        raise DatasetError(
            f"{path}: no COLMAP model (cameras.bin), *_meta.json or transforms.json in the folder"
        )
    data = load_json(path)
    if isinstance(data, dict) and "w2c" in data:
        return read_dynamic3dgs([path], wanted)
    return read_nerfstudio(path, wanted)


def rescaled(fit: CameraFit, width: int, height: int) -> CameraFit:
    """``fit`` for images of ``width`` x ``height`` (a calibration made at another resolution)."""
    if (fit.width, fit.height) == (width, height):
        return fit
    sx, sy = width / fit.width, height / fit.height
    K = fit.K.copy()
    K[0] *= sx
    K[1] *= sy
    distorted = None
    if fit.distorted is not None:
        import pycolmap

        distorted = pycolmap.Camera(fit.distorted.todict())
        distorted.rescale(width, height)
    return CameraFit(fit.w2c, K, width, height, distorted)


# ----- similarity transforms ----------------------------------------------------------------------
def centres_of(w2c: np.ndarray) -> np.ndarray:
    """[C, 3] camera centres of world-to-camera matrices [C, 4, 4]."""
    return -np.einsum("cji,cj->ci", w2c[:, :3, :3], w2c[:, :3, 3])


def transform_w2c(w2c: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World-to-camera [C, 4, 4] after the world moved by x' = s R x + t (the cameras keep their views)."""
    out = np.repeat(np.eye(4)[None], len(w2c), 0)
    out[:, :3, :3] = w2c[:, :3, :3] @ R.T
    out[:, :3, 3] = s * w2c[:, :3, 3] - np.einsum("cij,j->ci", out[:, :3, :3], t)
    return out


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3, 3] that takes the unit vector ``a`` to the unit vector ``b``."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1 + 1e-9:  # opposite: half a turn about any axis normal to a
        axis = np.cross(a, [1.0, 0, 0] if abs(a[0]) < 0.9 else [0, 1.0, 0])
        axis /= np.linalg.norm(axis)
        return 2 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1 + c)


def normalise(w2c: np.ndarray, distance: float = 4.0) -> tuple[float, np.ndarray, np.ndarray, dict]:
    """The similarity (s, R, t) that puts a rig round the origin: the point its cameras look at
    (``cameras.focus_point``; their mean centre for a rig that does not look inward) to the origin,
    the mean of their up vectors (-y of the OpenCV camera) to +z, their median distance from it to
    ``distance``. Returns it with a note for the report."""
    import torch

    from .cameras import focus_point

    centres = centres_of(w2c)
    focus = focus_point(torch.as_tensor(w2c))
    centre = centres.mean(0) if focus is None else focus.numpy()
    up = -w2c[:, 1, :3].mean(0)
    if np.linalg.norm(up) < 1e-6:
        up = np.array([0.0, 0.0, 1.0])
    R = _rotation_between(up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0]))
    median = float(np.median(np.linalg.norm(centres - centre, axis=1)))
    s = distance / max(median, 1e-12)
    note = {
        "centre": "the point the cameras look at" if focus is not None else "the cameras' mean centre",
        "up": "the cameras' mean up vector",
        "camera_distance": distance,
        "scale": s,
    }
    return s, R, -s * R @ centre, note


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """The similarity (s, R, t) minimising sum |dst - (s R src + t)|^2 over points [N, 3] (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    U, S, Vt = np.linalg.svd(b.T @ a / len(src))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / (a**2).sum(1).mean())
    return s, R, mu_d - s * R @ mu_s


def align_cameras(w2c: np.ndarray, truth: np.ndarray) -> dict:
    """How far cameras ``w2c`` [C, 4, 4] are from ``truth`` [C, 4, 4] (the same cameras, OpenCV axes)
    after the similarity that best puts their centres on the true ones: centre errors as a fraction of
    the true rig's radius (largest and mean), viewing-direction errors in degrees."""
    src, dst = centres_of(w2c), centres_of(truth)
    s, R, t = umeyama(src, dst)
    aligned = transform_w2c(w2c, s, R, t)
    radius = float(np.linalg.norm(dst - dst.mean(0), axis=1).max())
    centre_error = np.linalg.norm(centres_of(aligned) - dst, axis=1) / radius
    cosine = np.clip((aligned[:, 2, :3] * truth[:, 2, :3]).sum(-1), -1, 1)
    direction_error = np.degrees(np.arccos(cosine))
    rotation = [
        math.degrees(math.acos(np.clip((np.trace(a[:3, :3] @ b[:3, :3].T) - 1) / 2, -1, 1)))
        for a, b in zip(aligned, truth, strict=True)
    ]
    return {
        "rig_radius": radius,
        "centre_error_max": float(centre_error.max()),
        "centre_error_mean": float(centre_error.mean()),
        "direction_error_max_deg": float(direction_error.max()),
        "direction_error_mean_deg": float(direction_error.mean()),
        "rotation_error_max_deg": float(max(rotation)),
        "scale": s,
    }
