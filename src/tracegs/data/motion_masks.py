"""Motion masks of a static rig, derived from the capture itself: where each frame differs from its
camera's background plate.

A camera that stays still sees the still scene in most of its frames, so the per-pixel temporal median
of its frames is its background plate; the pixels of a frame that differ from that plate move. A
pixel moves where (``moving_pixels``, the defaults of ``MotionMaskSettings``):

1. the largest over the colour channels of |image - plate| exceeds ``threshold`` = 0.08 (of the
   [0, 1] range; about 15 times the median difference of a still pixel in the Panoptic capture), both
   as it is and blurred by a Gaussian of ``blur`` = 1 pixel (a pixel of sensor or JPEG noise is not
   above it once blurred; the edges stay where the image has them, not a blur's width outside);
2. after a closing by a 5x5 square with the holes filled (a shirt the colour of the wall stays one
   region with its arms), the connected regions of fewer than ``min_area`` = 20 pixels are dropped
   (noise, a blinking light of the dome);
3. what is left grows by a disc of ``dilate`` = 3 pixels (the scored region includes the edges a
   reconstruction blurs).

A camera with fewer than ``min_frames`` = 10 frames has no plate (``MotionMasks.mask`` is None), and
a camera whose pose changes between its frames (world-to-camera entries apart by more than
``pose_tolerance``) has none either: ``MotionMasks.of_split`` raises a ``DatasetError`` that says the
capture's cameras move. Frames without a camera id are grouped by pose, so a moving camera without
ids is many cameras of one frame each, none with a plate. A thing that stands still for more than
half of a camera's frames is part of its plate, and is not masked where it stands.

The pixel counts hold at 320x180 (CMU Panoptic's 640x360 at ``--downscale 2``). On the basketball
capture's four test cameras (``docs/figures/panoptic/motion_masks.png``, a row per camera: frame 55's
image, the camera's plate, then frames 55, 60 and 65 with the moving pixels tinted red) the players,
whole, and the flying ball are masked, and the dome, its floor and its lights are not; the plates of
two cameras keep a faint ghost of a player who stood in one place for much of the capture.

``tracegs masks --data SCENE --split test --out DIR`` writes the masks (``write_motion_masks``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .frames import Frame, SceneSplit

# The modules that read images (and torch) are imported where they are used: the CLI imports
# MotionMaskSettings for `tracegs masks --help`, which stays quick.

# T: frames of one camera, H, W: image size


@dataclass
class MotionMaskSettings:
    """The rule by which a pixel moves (the module docstring); pixel counts at the masks' size."""

    threshold: float = 0.08
    """A pixel moves where the largest channel of |image - plate| exceeds this (in [0, 1]), both as it
    is and blurred."""
    blur: float = 1.0
    """Sigma in pixels of the Gaussian blur of image - plate, which noise does not pass (0: no blur)."""
    min_area: int = 20
    """Connected moving regions of fewer pixels than this are noise, not motion."""
    dilate: int = 3
    """The moving pixels grow by a disc of this radius in pixels."""
    min_frames: int = 10
    """A camera with fewer frames than this gets no background plate (its masks are None)."""
    pose_tolerance: float = 1e-3
    """A camera moves where an entry of its world-to-camera matrix changes by more than this."""


def background_plate(images: np.ndarray) -> np.ndarray:
    """The per-pixel temporal median of one still camera's ``images`` [T, H, W, 3] -> [H, W, 3]."""
    return np.median(np.asarray(images, dtype=np.float32), axis=0)


def _disc(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return r[:, None] ** 2 + r[None, :] ** 2 <= radius**2


def moving_pixels(image: np.ndarray, plate: np.ndarray, settings: MotionMaskSettings) -> np.ndarray:
    """[H, W] bool: where ``image`` [H, W, 3] differs from its camera's ``plate`` [H, W, 3] (the rule of
    the module docstring)."""
    from scipy import ndimage

    diff = np.asarray(image, dtype=np.float32) - np.asarray(plate, dtype=np.float32)
    moving = np.abs(diff).max(axis=-1) > settings.threshold
    if settings.blur > 0:  # noise is not blurred above the threshold; the edges stay the image's own
        blurred = ndimage.gaussian_filter(diff, sigma=(settings.blur, settings.blur, 0))
        moving &= np.abs(blurred).max(axis=-1) > settings.threshold
    moving = ndimage.binary_closing(moving, structure=np.ones((5, 5), bool), border_value=0)
    moving = ndimage.binary_fill_holes(moving)
    if settings.min_area > 1 and moving.any():
        labels, n = ndimage.label(moving)
        area = np.bincount(labels.ravel(), minlength=n + 1)
        keep = area >= settings.min_area
        keep[0] = False
        moving = keep[labels]
    if settings.dilate > 0 and moving.any():
        moving = ndimage.binary_dilation(moving, structure=_disc(settings.dilate))
    return moving


def _camera_name(frames: list[Frame]) -> str:
    f = frames[0]
    return f"camera {f.camera_id}" if f.camera_id is not None else f"the camera of {f.image_path.name}"


def check_still(root: Path, cameras: dict[tuple, list[Frame]], tolerance: float) -> None:
    """A ``DatasetError`` naming the first camera of ``cameras`` (key -> its frames) whose pose changes
    between its frames by more than ``tolerance`` and the scene folder ``root``."""
    from .frames import DatasetError

    for frames in cameras.values():
        first = frames[0].camera.viewmat
        for f in frames[1:]:
            if float((f.camera.viewmat - first).abs().max()) > tolerance:
                raise DatasetError(
                    f"{root}: {_camera_name(frames)} moves (its pose in {f.image_path.name} is not the one "
                    f"in {frames[0].image_path.name}): the capture's cameras move, so no background plate "
                    "and no motion masks can be derived from it"
                )


class MotionMasks:
    """The motion masks of one split's frames: each still camera's plate (computed on first use and
    kept; the images are not) and, per frame, what differs from it."""

    def __init__(self, scene: SceneSplit, settings: MotionMaskSettings | None = None):
        from .frames import camera_key

        self.scene = scene
        self.settings = settings or MotionMaskSettings()
        self.cameras: dict[tuple, list[Frame]] = {}
        for f in sorted(scene.frames, key=lambda f: f.time):
            self.cameras.setdefault(camera_key(f), []).append(f)
        check_still(scene.root, self.cameras, self.settings.pose_tolerance)
        self._plates: dict[tuple, np.ndarray | None] = {}

    @classmethod
    def of_split(
        cls, data: Path, split: str, downscale: int = 1, settings: MotionMaskSettings | None = None
    ) -> MotionMasks:
        """The masks of the split ``split`` of the scene folder ``data``, images reduced by ``downscale``."""
        from .scene import load_scene

        return cls(load_scene(data, split, downscale), settings)

    def image(self, frame: Frame) -> np.ndarray:
        """[H, W, 3] float32: ``frame``'s image on the scene's background."""
        from .frames import load_image

        return load_image(frame, self.scene.background).numpy().astype(np.float32)

    def plate(self, frame: Frame) -> np.ndarray | None:
        """[H, W, 3] the background plate of ``frame``'s camera; None for a camera of too few frames."""
        from .frames import camera_key

        key = camera_key(frame)
        if key not in self._plates:
            frames = self.cameras.get(key, [])
            if len(frames) < self.settings.min_frames:
                self._plates[key] = None
            else:
                self._plates[key] = background_plate(np.stack([self.image(f) for f in frames]))
        return self._plates[key]

    def mask(self, frame: Frame) -> np.ndarray | None:
        """[H, W] bool at ``frame``'s size: the pixels that move; None when its camera has no plate."""
        from .frames import DatasetError

        plate = self.plate(frame)
        if plate is None:
            return None
        image = self.image(frame)
        if image.shape != plate.shape:
            raise DatasetError(
                f"{frame.image_path}: image of {image.shape[1]}x{image.shape[0]}, but the background plate "
                f"of its camera is {plate.shape[1]}x{plate.shape[0]} (another --downscale?)"
            )
        return moving_pixels(image, plate, self.settings)


def mask_path(root: Path, frame: Frame) -> Path:
    """Where a frame's mask goes under an output folder: its image's path under the scene folder
    ``root`` (under ``root/ims`` for a Panoptic capture), as a PNG; its name when it lies elsewhere."""
    image = Path(os.path.abspath(frame.image_path))
    base = Path(os.path.abspath(root))
    for folder in (base / "ims", base):
        try:
            return image.relative_to(folder).with_suffix(".png")
        except ValueError:
            continue
    return Path(frame.name).with_suffix(".png")


def read_motion_mask(path: Path, frame: Frame) -> np.ndarray:
    """[H, W] bool at ``frame``'s size: the mask file ``path`` that ``write_motion_masks`` wrote
    (non-zero = moves; one of an integer multiple of the size is sampled down); a ``DatasetError``
    naming the file when it is missing, unreadable or of another size."""
    from .frames import DatasetError
    from .masks import read_id_mask

    if not Path(path).is_file():
        raise DatasetError(f"{path}: no motion mask for the frame {frame.name}")
    return read_id_mask(Path(path), frame.height, frame.width) > 0


def write_motion_masks(
    data: Path,
    split: str,
    out: Path,
    downscale: int = 1,
    settings: MotionMaskSettings | None = None,
    figure: Path | None = None,
    figure_frames: tuple[int, ...] = (),
) -> dict:
    """`tracegs masks`: one PNG per frame of ``split`` under ``out`` (``mask_path``; 255 = moves),
    written atomically, and the ``figure`` (``motion_figure``) when given. Returns a report: per camera
    its frames and the mean share of moving pixels, or that it has no plate."""
    from ..utils import atomic_write_image

    masks = MotionMasks.of_split(Path(data), split, downscale, settings)
    out = Path(out)
    report = {"data": str(data), "split": split, "out": str(out), "settings": vars(masks.settings)}
    cameras = []
    for frames in masks.cameras.values():
        shares = []
        for f in frames:
            m = masks.mask(f)
            if m is None:
                break
            atomic_write_image(out / mask_path(masks.scene.root, f), m.astype(np.float32))
            shares.append(float(m.mean()))
        entry = {"camera": frames[0].camera_id, "frames": len(frames)}
        entry |= {"moving_share": float(np.mean(shares))} if shares else {"plate": None}
        cameras.append(entry)
    report["cameras"] = cameras
    report["written"] = sum(c["frames"] for c in cameras if "moving_share" in c)
    if figure is not None:
        report["figure"] = str(motion_figure(masks, figure, figure_frames))
    return report


def format_report(report: dict) -> str:
    """The console lines of ``write_motion_masks``'s report: each camera, then what was written."""
    lines = [
        f"camera {c['camera']}: {c['frames']} frames, "
        + (
            f"{100 * c['moving_share']:.1f}% of the pixels move"
            if "plate" not in c
            else "too few for a plate"
        )
        for c in report["cameras"]
    ]
    figure = f", the figure {report['figure']}" if "figure" in report else ""
    return "\n".join([*lines, f"{report['written']} masks in {report['out']}{figure}"])


def _overlay(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` [H, W, 3] with the moving pixels ``mask`` [H, W] tinted red and outlined in yellow."""
    from scipy import ndimage

    out = image.copy()
    out[mask] = 0.45 * out[mask] + 0.55 * np.array([1.0, 0.1, 0.1], np.float32)
    out[mask & ~ndimage.binary_erosion(mask)] = (1.0, 1.0, 0.0)
    return out


def motion_figure(masks: MotionMasks, path: Path, frames: tuple[int, ...] = ()) -> Path:
    """A PNG at ``path``: one row per camera with a plate, its first chosen frame's image, its plate,
    then each chosen frame with its mask (``_overlay``). ``frames`` are indices into each camera's
    frames in time order (default: a quarter, half and three quarters through)."""
    from ..utils import atomic_write_image
    from .frames import DatasetError

    rows = []
    for camera in masks.cameras.values():
        plate = masks.plate(camera[0])
        if plate is None:
            continue
        T = len(camera)
        chosen = [camera[min(max(i, 0), T - 1)] for i in (frames or (T // 4, T // 2, 3 * T // 4))]
        panels = [masks.image(chosen[0]), plate]
        panels += [_overlay(masks.image(f), masks.mask(f)) for f in chosen]
        gap = np.ones((plate.shape[0], 2, 3), np.float32)
        rows.append(np.concatenate([p for panel in panels for p in (panel, gap)][:-1], axis=1))
    if not rows:
        raise DatasetError(f"{masks.scene.root}: no camera of the split has a background plate")
    width = max(r.shape[1] for r in rows)
    gap = np.ones((2, width, 3), np.float32)
    grid = np.concatenate(
        [p for r in rows for p in (np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))), gap)][:-1]
    )
    return atomic_write_image(Path(path), grid)
