"""A synchronised rig's recordings on one clock: one video per camera (decoded with PyAV), or one
folder of frames per camera, sampled at common times.

The common clock: ``--offsets`` gives, per camera, the seconds cut from the start of its recording
so that the recordings line up (a camera started half a second before the others gets 0.5). The
output frame k is at common time ``start + k / fps``; each camera shows there its frame nearest in
time (frame index ``round((time + offset) * camera fps)``, the recording taken at its nominal,
constant rate). The times written to the scene are ``k / (T - 1)``, the Blender layout's [0, 1].

Recordings that differ are reconciled and the reconciliation is said (``Timing.notes``): other
rates are sampled at the slowest camera's rate (or ``--fps``, never above it); other lengths give
the span all of them cover; other sizes of one aspect ratio are resized to the smallest. Other
aspect ratios, a file that is no video, an empty folder and fewer than two cameras are refused
(``DatasetError``, naming the file).

T: output frames, C: cameras, H, W: image size
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from .frames import DatasetError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
FOLDER_FPS = 30.0
"""The rate of a folder of frames when ``--fps`` does not give one (folders carry no rate)."""


@dataclass
class Source:
    """One camera's recording: a video file, or a folder of frames (``images``, in order)."""

    name: str
    path: Path
    fps: float
    frames: int
    width: int
    height: int
    images: list[Path] | None = None

    @property
    def last_time(self) -> float:
        """Seconds from the first frame to the last."""
        return (self.frames - 1) / self.fps


def _open(path: Path):
    import av

    try:
        container = av.open(str(path))
    except Exception as e:  # PyAV raises several kinds (InvalidDataError, OSError, ...)
        raise DatasetError(f"{path}: not a video ({' '.join(str(e).split())})") from None
    if not container.streams.video:
        container.close()
        raise DatasetError(f"{path}: not a video (no video stream)")
    return container


def probe_video(path: Path) -> Source:
    """The rate, frame count and size of the video ``path`` (its first video stream)."""
    container = _open(path)
    try:
        stream = container.streams.video[0]
        rate = stream.average_rate or stream.guessed_rate or stream.base_rate
        fps = float(rate) if rate else 0.0
        width, height = stream.codec_context.width, stream.codec_context.height
        frames = stream.frames or sum(1 for p in container.demux(stream) if p.size)
    except Exception as e:
        raise DatasetError(f"{path}: not a readable video ({' '.join(str(e).split())})") from None
    finally:
        container.close()
    if not (fps > 0 and frames > 0 and width > 0 and height > 0):
        raise DatasetError(f"{path}: a video without frames, rate or size ({frames} frames at {fps:g} fps)")
    return Source(path.stem, path, fps, int(frames), int(width), int(height))


def image_folder(path: Path, fps: float | None) -> Source:
    """A camera's folder of frames (PNG or JPEG, in name order) at ``fps`` (``FOLDER_FPS`` if None)."""
    from ..image_metrics import read_image_array

    images = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not images:
        raise DatasetError(f"{path}: no frames (PNG or JPEG files) in the camera's folder")
    try:
        shape = read_image_array(images[0]).shape
    except ValueError as e:
        raise DatasetError(str(e)) from None
    return Source(path.name, path, float(fps or FOLDER_FPS), len(images), shape[1], shape[0], images)


def find_sources(
    videos: Path | None = None, images: Path | None = None, fps: float | None = None
) -> list[Source]:
    """The cameras of a rig: each file of the folder ``videos`` (a video each), or each folder under
    ``images`` (the frames of one camera each), in name order; at least two."""
    if (videos is None) == (images is None):
        raise ValueError(
            "give one of --videos DIR (a video per camera) or --images DIR (a folder per camera)"
        )
    root = Path(videos if videos is not None else images)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a folder")
    entries = sorted(p for p in root.iterdir() if not p.name.startswith("."))
    if videos is not None:
        sources = [probe_video(p) for p in entries if p.is_file()]
        what = "videos (one per camera)"
    else:
        sources = [image_folder(p, fps) for p in entries if p.is_dir()]
        what = "folders of frames (one per camera)"
    if not sources:
        raise DatasetError(f"{root}: empty folder, expected {what}")
    if len(sources) < 2:
        raise DatasetError(f"{root}: one camera ({sources[0].path.name}); a rig needs at least two {what}")
    names = [s.name for s in sources]
    for s in sources:
        if names.count(s.name) > 1:
            raise DatasetError(f"{s.path}: another recording has the camera name {s.name!r}")
    return sources


@dataclass
class Timing:
    """Which frame of each camera makes each output frame, and at which size."""

    fps: float
    start: float  # common-clock seconds of output frame 0
    count: int  # T
    offsets: list[float]  # [C] seconds cut from the start of each recording
    width: int
    height: int  # the output size (after --downscale)
    notes: list[str] = field(default_factory=list)

    @property
    def times(self) -> list[float]:
        """[T] the frames' normalised times in [0, 1]."""
        return [k / (self.count - 1) if self.count > 1 else 0.0 for k in range(self.count)]

    def indices(self, source: Source, c: int) -> list[int]:
        """[T] the frame of ``source`` (camera ``c``) at each output frame."""
        return [
            min(max(round((self.start + k / self.fps + self.offsets[c]) * source.fps), 0), source.frames - 1)
            for k in range(self.count)
        ]


def plan(
    sources: list[Source],
    fps: float | None = None,
    start: float = 0.0,
    end: float | None = None,
    offsets: tuple[float, ...] = (),
    downscale: int = 1,
) -> Timing:
    """The common frames of ``sources`` (module docstring): the rate, the span, the size."""
    C, notes = len(sources), []
    if offsets and len(offsets) != C:
        raise ValueError(
            f"--offsets gives {len(offsets)} values for {C} cameras ({', '.join(s.name for s in sources)})"
        )
    offsets = [float(o) for o in offsets] if offsets else [0.0] * C
    if downscale < 1:
        raise ValueError(f"--downscale must be a whole number >= 1, got {downscale}")
    slowest = min(sources, key=lambda s: s.fps)
    if fps is None:
        fps = slowest.fps
        if any(abs(s.fps - fps) > 1e-3 for s in sources):
            rates = ", ".join(f"{s.name} {s.fps:g}" for s in sources)
            notes.append(f"the cameras' rates differ ({rates} fps): sampled at the slowest, {fps:g} fps")
    elif not fps > 0:
        raise ValueError(f"--fps must be positive, got {fps}")
    elif fps > slowest.fps + 1e-3:
        raise DatasetError(f"{slowest.path}: --fps {fps:g} is above its rate, {slowest.fps:g} fps")
    first = max(start, max(-o for o in offsets))
    last = min(s.last_time - o for s, o in zip(sources, offsets, strict=True))
    if end is not None:
        last = min(last, end)
    lengths = {round(s.last_time, 3) for s in sources}
    if len(lengths) > 1:
        notes.append(
            f"the recordings differ in length ({min(lengths):g} to {max(lengths):g} s): the span all of them "
            "cover is used"
        )
    if last < first - 1e-9:
        raise DatasetError(
            f"{sources[0].path.parent}: no common span: from {first:g} s to {last:g} s (see --start, --end, --offsets)"
        )
    count = math.floor((last - first) * fps + 1e-6) + 1
    width, height = _common_size(sources, notes)
    if width // downscale < 8 or height // downscale < 8:
        raise ValueError(f"--downscale {downscale} leaves images of under 8 pixels ({width}x{height})")
    return Timing(fps, first, count, offsets, width // downscale, height // downscale, notes)


def _common_size(sources: list[Source], notes: list[str]) -> tuple[int, int]:
    """The smallest size of ``sources``; a DatasetError naming the first of another aspect ratio."""
    small = min(sources, key=lambda s: s.width * s.height)
    for s in sources:
        if (
            abs(s.width * small.height - s.height * small.width)
            > max(s.width, s.height) * 0.01 * small.height
        ):
            raise DatasetError(
                f"{s.path}: {s.width}x{s.height}, another aspect ratio than {small.path.name}'s "
                f"{small.width}x{small.height}; crop the recordings to one aspect ratio"
            )
    if any((s.width, s.height) != (small.width, small.height) for s in sources):
        sizes = ", ".join(f"{s.name} {s.width}x{s.height}" for s in sources)
        notes.append(
            f"the cameras' sizes differ ({sizes}): resized to the smallest, {small.width}x{small.height}"
        )
    return small.width, small.height


def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """[H, W, 3] uint8 ``image`` at ``width`` x ``height`` (area averaging; the image if it has that size)."""
    if image.shape[:2] == (height, width):
        return image
    import torch

    x = torch.from_numpy(np.ascontiguousarray(image)).permute(2, 0, 1)[None].float()
    x = torch.nn.functional.interpolate(x, size=(height, width), mode="area")
    return x[0].permute(1, 2, 0).round().clamp(0, 255).to(torch.uint8).numpy()


def _video_frames(source: Source) -> Iterator[np.ndarray]:
    container = _open(source.path)
    try:
        for frame in container.decode(video=0):
            yield frame.to_ndarray(format="rgb24")
    except DatasetError:
        raise
    except Exception as e:
        raise DatasetError(f"{source.path}: cannot decode ({' '.join(str(e).split())})") from None
    finally:
        container.close()


def _folder_frames(source: Source) -> Iterator[np.ndarray]:
    from ..image_metrics import read_image_array

    for path in source.images or []:
        try:
            image = read_image_array(path)
        except ValueError as e:
            raise DatasetError(str(e)) from None
        if image.dtype != np.uint8:  # 16-bit PNGs
            image = np.round(image / np.iinfo(image.dtype).max * 255).astype(np.uint8)
        image = image[..., None] if image.ndim == 2 else image
        yield (
            np.broadcast_to(image[..., :3], (*image.shape[:2], 3)) if image.shape[-1] < 3 else image[..., :3]
        )


def decode(source: Source, c: int, timing: Timing) -> Iterator[tuple[int, np.ndarray]]:
    """(k, [H, W, 3] uint8) for each output frame k of camera ``c``, in order of k, at the output size."""
    wanted: dict[int, list[int]] = {}
    for k, i in enumerate(timing.indices(source, c)):
        wanted.setdefault(i, []).append(k)
    last = max(wanted)
    frames = _video_frames(source) if source.images is None else _folder_frames(source)
    i = -1
    for i, image in enumerate(frames):
        if image.shape[1] * source.height != image.shape[0] * source.width:
            raise DatasetError(
                f"{source.path}: frame {i} is {image.shape[1]}x{image.shape[0]}, not {source.width}x{source.height}"
            )
        for k in wanted.get(i, ()):
            yield k, resize(image, timing.width, timing.height)
        if i >= last:
            break
    if i < last:
        raise DatasetError(f"{source.path}: ends after {i + 1} frames, expected at least {last + 1}")


def write_video(path: Path, frames: list[np.ndarray] | np.ndarray, fps: float, crf: int = 12) -> Path:
    """Encode [T, H, W, 3] uint8 ``frames`` as an H.264 MP4 (even sizes; the synthetic rigs' videos)."""
    import av

    frames = [np.asarray(f, dtype=np.uint8) for f in frames]
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=Fraction(fps).limit_denominator(1001))
        stream.width, stream.height = frames[0].shape[1], frames[0].shape[0]
        stream.pix_fmt = "yuv444p"
        stream.options = {"crf": str(crf), "preset": "medium"}
        for image in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(image, format="rgb24")))
        container.mux(stream.encode())
    return path
