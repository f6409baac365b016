"""The frozen-appearance ceiling of a synthetic scene: how well can a model that only moves Gaussians
predict its future?

TRACE, like every deformation or dynamics model of Gaussians, gives each Gaussian one colour for all
time: a surface point looks in the future as it looked when it was fitted. The synthetic scenes are
lit by a sun (``render.Lighting``), so a part that turns changes its shading (a face turns away from
the sun) and moving parts sweep shadows over static ones; no motion of Gaussians renders either.
:func:`frozen_appearance` renders chosen frames with the exact geometry and motion but with each
surface point's appearance taken from other frames (``appearance_frames``, averaged when there are
several), and scores them against the ground truth:

- A rigid part p that has turned by R = R_p(t) R_p(t_k)^T since an appearance frame t_k is rendered at
  time t under the sun rotated by R: a surface normal n(t) = R n(t_k) then meets the light at the
  angle it met it at t_k, so its shading and self-shadowing are those of t_k. (Translation does not
  change a sun's shading.) The frame's own sample seed is used, so anti-aliasing noise is the data's.
- A static part's pixel takes what the same camera saw there at the appearance frames where it saw
  the same part (the shadows of moving parts stay where they were then); where it saw the part at no
  appearance frame (disoccluded), the ground truth is used, which makes the bound optimistic there.
- Parts that translate without turning, and the background, are the ground truth.

:func:`appearance_ceiling` gives two bounds for a scene's extrapolation split: ``handover`` (appearance
of the handover time t_h, where TRACE's extrapolation starts) and ``mean`` (the mean appearance over
the training frames: the constant colour that fits them best in L2, all that a model fitted on the
whole span with one colour per Gaussian can learn). Before scoring, it re-renders a few stored frames
and checks they are reproduced byte for byte, so the bound comes from the data's renderer, cameras
and samples.

# H, W: image size, P: parts
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import imageio.v3 as iio
import numpy as np

from .cameras import make_rig
from .motion import transforms_at
from .render import Lighting, build_scene, make_sensors, pose, render_rgba, to_srgb8
from .scenes import get_scene
from .writer import image_name, motion_bounds


def _composite(rgba8: np.ndarray) -> np.ndarray:
    """uint8 RGBA (straight alpha) -> float RGB on white, as the data loader reads a frame."""
    x = rgba8.astype(np.float64) / 255.0
    return x[..., :3] * x[..., 3:] + (1.0 - x[..., 3:])


def turn(motion, t: float, t_k: float) -> np.ndarray:
    """[3, 3] rotation a part with ``motion`` has made from time ``t_k`` to time ``t``."""
    r = transforms_at([motion], np.array([t, t_k]))[:, 0, :3, :3]
    return r[0] @ r[1].T


class SceneFolder:
    """A ``tracegs synth`` folder with what it takes to re-render its frames."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        path = self.folder / "gt" / "synth.json"
        if not path.is_file():
            raise FileNotFoundError(
                f"{path}: not found; the ceiling needs a folder written by `tracegs synth`"
            )
        s = json.loads(path.read_text())
        self.views, self.frames, self.seed, self.spp = s["views"], s["frames"], s["seed"], s["spp"]
        self.train_frames = s["train_frames"]
        default = Lighting()  # folders written before the light was a setting have the default one
        self.lighting = Lighting(
            ambient=s.get("ambient", default.ambient), sun_irradiance=s.get("sun", default.sun_irradiance)
        )
        self.spec = get_scene(s["scene"])
        self.motions = [p.motion for p in self.spec.parts]
        bounds = motion_bounds(self.spec)
        rig = make_rig(self.views, s["train_views"], bounds.center, bounds.radius, self.seed)
        self.sensors = [
            make_sensors(c2w, rig.camera_angle_x, s["resolution"], self.spp)[0] for c2w in rig.c2w
        ]
        self.times = np.arange(self.frames) / (self.frames - 1)
        transforms = transforms_at(self.motions, self.times)  # [F, P, 4, 4]
        self.turning = [
            p for p in range(len(self.motions)) if not np.allclose(transforms[:, p, :3, :3], np.eye(3))
        ]
        self.static = [p for p in range(len(self.motions)) if np.allclose(transforms[:, p], np.eye(4))]
        self.names = ["background"] + [p.name for p in self.spec.parts]

    def stored(self, c: int, f: int) -> tuple[np.ndarray, np.ndarray]:
        """(RGB on white [H, W, 3], part ids [H, W]) of a stored frame, whichever split holds it."""
        name = image_name(c, f, self.views, self.frames)
        for split in ("train", "val", "test"):
            image, mask = self.folder / split / name, self.folder / "gt" / "masks" / split / name
            if image.is_file() and mask.is_file():
                return _composite(iio.imread(image)), iio.imread(mask).astype(np.int64)
        raise FileNotFoundError(f"{self.folder}: no image and mask of camera {c}, frame {f} ({name})")

    def render(self, scene, c: int, f: int) -> np.ndarray:
        """Camera ``c``'s view of a posed scene with frame ``f``'s sample seed, as the data stores it."""
        seed = ((self.seed * self.frames + f) * self.views + c) % 2**32
        return _composite(to_srgb8(render_rgba(scene, self.sensors[c], seed=seed)))

    def lit_as_at(self, part: int, f: int, k: int):
        """The scene posed at frame ``f`` under the sun turned as ``part`` turned since frame ``k``."""
        sun = turn(self.motions[part], self.times[f], self.times[k]) @ np.asarray(self.lighting.sun_direction)
        lighting = dataclasses.replace(self.lighting, sun_direction=tuple(float(x) for x in sun))
        scene = build_scene(self.spec, lighting)
        pose(scene, transforms_at(self.motions, self.times[f]))
        return scene

    def check_reproduction(self, frames: list[int]) -> int:
        """Re-render the first and last camera of ``frames``; raise if a byte differs. Returns the count."""
        scene = build_scene(self.spec, self.lighting)
        for f in frames:
            pose(scene, transforms_at(self.motions, self.times[f]))
            for c in (0, self.views - 1):
                if not np.array_equal(self.render(scene, c, f), self.stored(c, f)[0]):
                    raise RuntimeError(
                        f"{self.folder}: re-rendering camera {c}, frame {f} does not reproduce the data"
                    )
        return 2 * len(frames)


def frozen_appearance(scene: SceneFolder, appearance_frames: list[int], score_frames: list[int]) -> dict:
    """Score ``score_frames`` (every camera) rendered with the appearance of ``appearance_frames``."""
    from ...image_metrics import mae_psnr

    n = len(scene.names)
    error, pixels, frame_mse = np.zeros(n), np.zeros(n), []
    past = {c: [scene.stored(c, k) for k in appearance_frames] for c in range(scene.views)}
    for f in score_frames:
        lit = {(p, k): scene.lit_as_at(p, f, k) for p in scene.turning for k in appearance_frames}
        for c in range(scene.views):
            gt, ids = scene.stored(c, f)
            pred = gt.copy()
            for p in scene.turning:
                here = ids == p + 1
                if here.any():
                    pred[here] = np.mean(
                        [scene.render(lit[p, k], c, f)[here] for k in appearance_frames], axis=0
                    )
            for p in scene.static:
                seen = [(ids_k == p + 1) & (ids == p + 1) for _, ids_k in past[c]]
                total = sum(
                    np.where(s[..., None], img, 0.0) for s, (img, _) in zip(seen, past[c], strict=True)
                )
                count = np.sum(seen, axis=0)
                pred[count > 0] = total[count > 0] / count[count > 0, None]
            err = ((pred - gt) ** 2).mean(-1)
            frame_mse.append(float(err.mean()))
            error += np.bincount(ids.ravel(), weights=err.ravel(), minlength=n)
            pixels += np.bincount(ids.ravel(), minlength=n)
    return {
        "appearance_times": [float(scene.times[k]) for k in appearance_frames],
        "frames_scored": len(frame_mse),
        "mse": float(np.mean(frame_mse)),
        "mae_psnr": mae_psnr(frame_mse),
        "per_part": {
            scene.names[i]: {
                "pixel_share": float(pixels[i] / pixels.sum()),
                "error_share": float(error[i] / error.sum()) if error.sum() > 0 else 0.0,
                "psnr": mae_psnr([error[i] / pixels[i]]) if error[i] > 0 else None,  # None: exact
            }
            for i in range(n)
            if pixels[i] > 0
        },
    }


def appearance_ceiling(folder: str | Path, handover_frames: float = 4.0, mean_frames: int = 12) -> dict:
    """The ``handover`` and ``mean`` bounds of a scene's extrapolation split (every camera, t > t_max).

    ``handover_frames``: frames before t_max where the extrapolation starts (``extrapolation.handover_frames``);
    ``mean_frames``: training frames, evenly spaced from t = 0 to t_max, averaged by the ``mean`` bound.
    """
    scene = SceneFolder(folder)
    f_end = scene.train_frames - 1
    future = list(range(f_end + 1, scene.frames))
    checked = scene.check_reproduction(future[:3])
    spread = np.linspace(0, f_end, min(mean_frames, f_end + 1))
    handover = int(round(f_end - handover_frames))
    return {
        "scene": scene.spec.name,
        "handover_time": float(scene.times[handover]),
        "frames_checked": checked,
        "handover": frozen_appearance(scene, [handover], future),
        "mean": frozen_appearance(scene, sorted({int(round(k)) for k in spread}), future),
    }
