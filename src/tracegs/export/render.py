"""Render a trained run: one image at any time and camera, or a video sweeping camera and time."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from ..data.cameras import Camera, look_at_viewmat
from ..data.scene import available_splits, load_scene
from ..extrapolate import Predictor
from ..run import load_run, run_data
from ..utils import atomic_write_image


def orbit_camera(reference: list[Camera], azimuth_deg: float, elevation_deg: float | None = None) -> Camera:
    """A camera on the training cameras' sphere, looking at their common target, at the given azimuth."""
    centers = torch.stack([c.center.cpu() for c in reference])
    target = torch.zeros(3)
    radius = float(centers.norm(dim=-1).mean())
    # "up" = the mean of the cameras' up directions (OpenCV: -y axis of each camera in world coordinates)
    up = torch.nn.functional.normalize(
        -torch.stack([c.viewmat[1, :3].cpu() for c in reference]).mean(0), dim=0
    )
    if elevation_deg is None:
        elevation_deg = math.degrees(
            math.asin(float((centers / centers.norm(dim=-1, keepdim=True) @ up).mean()))
        )
    # an orthonormal frame around "up"
    a = torch.tensor([1.0, 0.0, 0.0]) if abs(float(up[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0])
    e1 = torch.nn.functional.normalize(a - (a @ up) * up, dim=0)
    e2 = torch.linalg.cross(up, e1)
    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    eye = radius * (math.cos(el) * (math.cos(az) * e1 + math.sin(az) * e2) + math.sin(el) * up)
    ref = reference[0]
    return Camera(look_at_viewmat(eye, target, up), ref.K.cpu(), ref.width, ref.height)


def pick_camera(data: Path, spec: str, downscale: int = 1) -> Camera:
    """``SPLIT:INDEX`` of a dataset camera, or ``orbit:AZIMUTH_DEG``; a ValueError naming ``--camera``
    and the choices for any other spec."""
    kind, _, value = spec.partition(":")
    splits = available_splits(data)
    usage = f"expected SPLIT:INDEX with SPLIT one of {', '.join(splits) or '(none found in ' + str(data) + ')'}, or orbit:DEGREES"
    if kind == "orbit":
        try:
            azimuth = float(value or 0)
        except ValueError:
            azimuth = math.nan
        if not math.isfinite(azimuth):
            raise ValueError(f"--camera {spec!r}: the orbit's azimuth must be a number of degrees; {usage}")
        cams = [f.camera for f in load_scene(data, "train", downscale).frames]
        return orbit_camera(cams, azimuth)
    if kind not in splits:
        raise ValueError(f"--camera {spec!r}: no split {kind!r} in {data}; {usage}")
    frames = load_scene(data, kind, downscale).frames
    if not (value or "0").isdigit() or not 0 <= int(value or 0) < len(frames):
        raise ValueError(
            f"--camera {spec!r}: split {kind!r} has {len(frames)} frames, choose an index in 0-{len(frames) - 1}"
        )
    return frames[int(value or 0)].camera


IMAGE_SUFFIXES, VIDEO_SUFFIXES = (".png", ".jpg", ".jpeg"), (".mp4", ".gif")


def _check_out(out: Path | None, video: bool) -> None:
    suffixes = VIDEO_SUFFIXES if video else IMAGE_SUFFIXES
    if out is not None and Path(out).suffix.lower() not in suffixes:
        kind = "a video" if video else "an image"
        raise ValueError(f"--out {out}: {kind} is written as {' or '.join(suffixes)}")


def render_command(
    run: Path,
    out: Path | None = None,
    time: float = 1.0,
    camera: str = "test:0",
    video: bool = False,
    t_end: float = 1.5,
    frames: int = 90,
    data: Path | None = None,
    device: str = "auto",
) -> Path:
    """``tracegs render``: one image of ``run`` at ``time`` from ``camera`` (``pick_camera``), or with
    ``video`` a sweep of ``frames`` frames while time runs 0 -> ``t_end``; returns the file written.
    The times, the camera and ``out`` are checked before anything is rendered."""
    _check_out(out, video)
    if video and (isinstance(frames, bool) or not isinstance(frames, int) or frames < 1):
        raise ValueError(f"--frames must be a positive integer, got {frames}")
    loaded = load_run(run, device, data)
    predictor, cfg = loaded.predictor, loaded.config
    data = run_data(cfg, data)  # (a clear error when the scene is not there)
    predictor.check_time(t_end if video else time, "--t-end" if video else "--time")
    if not video:
        cam = pick_camera(data, camera, cfg.downscale).to(predictor.device)
        image = predictor.render(cam, time)
        out = Path(out or Path(run) / "renders" / f"{camera.replace(':', '_')}_t{time:.3f}.png")
        return atomic_write_image(out, image)
    out = Path(out or Path(run) / "renders" / "sweep.mp4")
    images = sweep(predictor, data, t_end, frames, cfg.downscale)
    return write_video(images, out, total=frames)


def sweep(predictor: Predictor, data, t_end: float, frames: int, downscale: int = 1, paint=None):
    """The frames [H, W, 3] uint8 of a sweep: the camera orbits once while time runs from 0 to
    ``t_end``; ``paint(image, gaussians, camera)`` -> image, when given, draws on each rendered image
    (``gaussians``: their geometry at that frame's time)."""
    cams = [f.camera for f in load_scene(data, "train", downscale).frames]
    for k in range(frames):
        t = t_end * k / max(frames - 1, 1)
        cam = orbit_camera(cams, 360.0 * k / frames).to(predictor.device)
        gaussians = predictor.gaussians_at(t)
        img = predictor.render(cam, gaussians=gaussians).cpu().numpy()
        if paint is not None:
            img = paint(img, gaussians, cam)
        yield (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def even_size(image: np.ndarray) -> np.ndarray:
    """``image`` [H, W, C] padded by repeating its last row / column to an even height and width
    (H.264 in yuv420p, the format every player reads, needs both even)."""
    h, w = image.shape[:2]
    return np.pad(image, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")


def _ffmpeg_available() -> bool:
    try:
        import imageio_ffmpeg

        imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return False
    return True


def _check_video(path: Path, shape: tuple[int, ...]) -> None:
    """Raise OSError unless ``path`` is a non-empty video whose first frame imageio reads back at ``shape``."""
    import imageio.v3 as iio

    try:
        first = next(iter(iio.imiter(path))) if path.stat().st_size > 0 else None
    except Exception as e:  # imageio raises many types for an unreadable file
        raise OSError(f"{path}: the video written cannot be read back ({type(e).__name__}: {e})") from None
    if first is None or first.shape[:2] != shape[:2]:
        raise OSError(f"{path}: the video written is empty or of another size than its frames")


def write_video(images, out: Path, total: int | None = None) -> Path:
    """Write the frames ``images`` (uint8 [H, W, 3]) as MP4 at 24 fps (GIF when ``out`` says so, or when
    there is no ffmpeg: then next to ``out``), atomically, padded to an even size; the file is read back
    before it replaces ``out``. Returns the path written. ``total``: the frame count, for the progress bar."""
    import imageio.v2 as imageio

    progress = tqdm(
        images, total=total, desc=f"video {Path(out).name}", unit="frame", disable=None, leave=False
    )
    images = [even_size(img) for img in progress]
    if not images:
        raise ValueError(f"{out}: a video needs at least one frame")
    out = Path(out)
    if out.suffix == ".mp4" and not _ffmpeg_available():
        out = out.with_suffix(".gif")
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")
    try:
        if out.suffix == ".mp4":
            imageio.mimwrite(tmp, images, fps=24, macro_block_size=1)
        else:
            imageio.mimwrite(tmp, images, duration=1 / 24)
        _check_video(tmp, images[0].shape)
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)
    return out
