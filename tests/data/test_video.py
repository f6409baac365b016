"""Decoding a rig's recordings on one clock (``tracegs.data.video``): small generated videos whose
frames carry their time as their brightness, so every sampled frame can be checked."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

pytest.importorskip("av")

from tracegs.data.frames import DatasetError  # noqa: E402
from tracegs.data.video import decode, find_sources, plan, write_video  # noqa: E402

STEP = 8  # brightness per frame of the event clock at 10 fps


def _clip(path: Path, count: int, fps: float = 10.0, first: int = 0, size=(48, 32), every: int = 1) -> Path:
    """A video of ``count`` flat frames; frame i shows the event clock's frame ``first + i / every``
    (at ``fps``), as brightness STEP per frame of a 10 fps clock."""
    w, h = size
    frames = [np.full((h, w, 3), STEP * (first + i // every), np.uint8) for i in range(count)]
    return write_video(path, frames, fps)


def _levels(source, c, timing) -> list[int]:
    return [round(float(image.mean()) / STEP) for _, image in decode(source, c, timing)]


def test_decode_samples_every_frame_and_normalises_times(tmp_path):
    for name in ("a", "b", "c"):
        _clip(tmp_path / f"{name}.mp4", 20)
    sources = find_sources(videos=tmp_path)
    assert [s.name for s in sources] == ["a", "b", "c"]
    assert (sources[0].fps, sources[0].frames, sources[0].width, sources[0].height) == (10.0, 20, 48, 32)
    timing = plan(sources)
    assert timing.count == 20 and timing.notes == []
    assert timing.times[0] == 0 and timing.times[-1] == 1 and np.allclose(np.diff(timing.times), 1 / 19)
    assert _levels(sources[1], 1, timing) == list(range(20))


def test_start_end_fps_and_downscale(tmp_path):
    for name in ("a", "b"):
        _clip(tmp_path / f"{name}.mp4", 20)
    sources = find_sources(videos=tmp_path)
    timing = plan(sources, fps=5.0, start=0.4, end=1.6, downscale=2)
    assert timing.count == 7  # 0.4, 0.6, ..., 1.6 s
    assert _levels(sources[0], 0, timing) == [4, 6, 8, 10, 12, 14, 16]
    assert (timing.width, timing.height) == (24, 16)
    assert next(decode(sources[0], 0, timing))[1].shape == (16, 24, 3)


def test_offsets_line_the_recordings_up(tmp_path):
    _clip(tmp_path / "a.mp4", 20)
    # b started 0.5 s early: its frame i is a's frame i - 5 (its first five show something else)
    frames = [np.full((32, 48, 3), STEP * max(i - 5, 0) + (100 if i < 5 else 0), np.uint8) for i in range(20)]
    write_video(tmp_path / "b.mp4", frames, 10.0)
    sources = find_sources(videos=tmp_path)
    timing = plan(sources, offsets=(0.0, 0.5))
    assert timing.count == 15  # b has 1.5 s left after its 0.5 s cut
    assert _levels(sources[0], 0, timing) == _levels(sources[1], 1, timing) == list(range(15))
    with pytest.raises(ValueError, match="--offsets gives 1 values for 2 cameras"):
        plan(sources, offsets=(0.5,))


def test_other_rates_lengths_and_sizes_are_reconciled_and_said(tmp_path):
    _clip(tmp_path / "a.mp4", 20)
    _clip(tmp_path / "b.mp4", 30, fps=20.0, every=2, size=(96, 64))  # twice the rate and size, 1.5 s
    sources = find_sources(videos=tmp_path)
    timing = plan(sources)
    assert timing.fps == 10.0 and timing.count == 15
    assert _levels(sources[1], 1, timing) == list(range(15))
    notes = " ".join(timing.notes)
    assert (
        "rates differ" in notes and "differ in length" in notes and "resized to the smallest, 48x32" in notes
    )
    assert next(decode(sources[1], 1, timing))[1].shape == (32, 48, 3)
    with pytest.raises(DatasetError, match="a.mp4: --fps 20 is above its rate, 10 fps"):
        plan(sources, fps=20.0)


def test_folders_of_frames(tmp_path):
    for name in ("left", "right"):
        (tmp_path / name).mkdir()
        for i in range(6):
            iio.imwrite(tmp_path / name / f"{i:03d}.png", np.full((16, 16, 3), STEP * i, np.uint8))
    sources = find_sources(images=tmp_path, fps=12.0)
    assert [(s.name, s.frames, s.fps) for s in sources] == [("left", 6, 12.0), ("right", 6, 12.0)]
    timing = plan(sources)
    assert _levels(sources[1], 1, timing) == list(range(6))


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda d: None, "empty folder"),
        (lambda d: _clip(d / "a.mp4", 5), "one camera"),
        (lambda d: (_clip(d / "a.mp4", 5), (d / "notes.txt").write_text("hello")), "notes.txt: not a video"),
        (
            lambda d: (_clip(d / "a.mp4", 5), _clip(d / "b.mp4", 5, size=(48, 48))),
            "b.mp4: 48x48, another aspect",
        ),
    ],
)
def test_bad_recordings_are_refused_naming_the_file(tmp_path, make, message):
    make(tmp_path)
    with pytest.raises(DatasetError, match=message):
        plan(find_sources(videos=tmp_path))


def test_an_empty_camera_folder_is_named(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    iio.imwrite(tmp_path / "a" / "0.png", np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(DatasetError, match=r"/b: no frames"):
        find_sources(images=tmp_path)
