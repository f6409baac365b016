"""Render a trained run: one image at any time and camera, or a video sweeping camera and time."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from ..data.cameras import Camera, look_at_viewmat
from ..data.scene import load_scene
from ..extrapolate import gaussians_at
from ..run import load_run
from ..utils import atomic_write_image


@torch.no_grad()
def render_at(model, state, t: float, camera: Camera, background: torch.Tensor) -> torch.Tensor:
    """Image [H, W, 3] of the scene at time ``t`` (extrapolated past the run's training span with its
    post-training ``state``) seen by ``camera``."""
    return render_gaussians(model, gaussians_at(model, state, t), camera, background)


@torch.no_grad()
def render_gaussians(model, gaussians: dict, camera: Camera, background: torch.Tensor) -> torch.Tensor:
    """Image [H, W, 3] of the Gaussians whose geometry at some time is ``gaussians`` (``gaussians_at``)."""
    return model.render(gaussians, camera, model.cfg.sh_degree, background).image.clamp(0, 1)


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
    """``SPLIT:INDEX`` of a dataset camera, or ``orbit:AZIMUTH_DEG``."""
    kind, _, value = spec.partition(":")
    if kind == "orbit":
        cams = [f.camera for f in load_scene(data, "train", downscale).frames]
        return orbit_camera(cams, float(value or 0))
    frames = load_scene(data, kind, downscale).frames
    index = int(value or 0)
    if not 0 <= index < len(frames):
        raise ValueError(f"camera {spec!r}: split {kind!r} has {len(frames)} frames")
    return frames[index].camera


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
    loaded = load_run(run, device)
    model, cfg, state = loaded.model, loaded.config, loaded.state
    data = Path(data or cfg.data)
    background = torch.tensor(load_scene(data, "train").background, device=model.aabb.device)
    if not video:
        cam = pick_camera(data, camera, cfg.downscale).to(model.aabb.device)
        image = render_at(model, state, time, cam, background)
        out = Path(out or Path(run) / "renders" / f"{camera.replace(':', '_')}_t{time:.3f}.png")
        return atomic_write_image(out, image)
    out = Path(out or Path(run) / "renders" / "sweep.mp4")
    return render_sweep_video(model, state, data, out, t_end, frames, background, cfg.downscale)


def render_sweep_video(model, state, data, out: Path, t_end, frames, background, downscale=1) -> Path:
    """A video whose camera orbits once while time runs from 0 to ``t_end``."""
    return write_video(sweep(model, state, data, t_end, frames, background, downscale), out)


def sweep(model, state, data, t_end: float, frames: int, background, downscale: int = 1, paint=None):
    """The frames [H, W, 3] uint8 of a sweep: the camera orbits once while time runs from 0 to
    ``t_end``; ``paint(image, gaussians, camera)`` -> image, when given, draws on each rendered image
    (``gaussians``: their geometry at that frame's time)."""
    cams = [f.camera for f in load_scene(data, "train", downscale).frames]
    for k in range(frames):
        t = t_end * k / max(frames - 1, 1)
        cam = orbit_camera(cams, 360.0 * k / frames).to(model.aabb.device)
        gaussians = gaussians_at(model, state, t)
        img = render_gaussians(model, gaussians, cam, background).cpu().numpy()
        if paint is not None:
            img = paint(img, gaussians, cam)
        yield (np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)


def write_video(images, out: Path) -> Path:
    """Write the frames ``images`` (uint8 [H, W, 3]) as MP4 at 24 fps (GIF when ``out`` says so, or when
    imageio finds no ffmpeg: then next to ``out``), atomically; returns the path written."""
    import imageio.v2 as imageio

    images = list(images)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")
    try:
        if out.suffix == ".mp4":
            import imageio_ffmpeg  # noqa: F401  (the ffmpeg binary imageio writes MP4 with)

            imageio.mimwrite(tmp, images, fps=24, macro_block_size=1)
        else:
            imageio.mimwrite(tmp, images, duration=1 / 24)
    except Exception:  # no ffmpeg: fall back to a GIF next to the requested path
        out = out.with_suffix(".gif")
        tmp = out.with_name(f".{out.stem}.tmp.gif")
        imageio.mimwrite(tmp, images, duration=1 / 24)
    tmp.replace(out)
    return out
