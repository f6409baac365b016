"""What a command writes is checked before it says so: a video at an odd image size plays, a video that
could not be written leaves no file behind and no path printed; presets pass their own validation."""

from __future__ import annotations

from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from tests.conftest import write_tiny_scene
from tracegs.cli import main
from tracegs.config import PRESETS, validate
from tracegs.export.render import even_size, write_video
from tracegs.extrapolate import check_time


def test_a_video_at_an_odd_image_size_is_written_and_plays(tmp_path, capsys):
    scene = write_tiny_scene(tmp_path / "scene", size=15)
    run = tmp_path / "run"
    main(["train", "--data", str(scene), "--run", str(run), "--preset", "tiny", "--device", "cpu"])
    out = tmp_path / "sweep.mp4"
    capsys.readouterr()
    main(["render", "--run", str(run), "--video", "--frames", "3", "--out", str(out), "--device", "cpu"])
    printed = capsys.readouterr().out.strip()
    written = Path(printed)
    assert written.is_file() and written.stat().st_size > 0
    frames = list(iio.imiter(written))
    assert len(frames) == 3 and frames[0].shape[:2] == (16, 16)  # padded to an even size
    assert not list(tmp_path.glob(".sweep*"))  # no temporary file left


def test_even_size_repeats_the_last_row_and_column():
    image = np.arange(3 * 5 * 3, dtype=np.uint8).reshape(3, 5, 3)
    padded = even_size(image)
    assert padded.shape == (4, 6, 3)
    assert (padded[:3, :5] == image).all()
    assert (padded[3, :5] == image[2]).all() and (padded[:3, 5] == image[:, 4]).all()
    assert even_size(padded).shape == (4, 6, 3)


def test_a_video_that_cannot_be_read_back_is_an_error_and_leaves_nothing(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    monkeypatch.setattr(imageio, "mimwrite", lambda path, *a, **k: Path(path).write_bytes(b""))
    out = tmp_path / "v.mp4"
    frames = [np.zeros((8, 8, 3), np.uint8)] * 2
    with pytest.raises(OSError, match="empty"):
        write_video(frames, out)
    assert list(tmp_path.iterdir()) == []


def test_render_times_are_checked_against_the_training_span():
    assert check_time(7.5, 0.75) == 7.5
    with pytest.raises(ValueError, match="beyond the limit 7.5"):
        check_time(7.6, 0.75)
    assert check_time(1.0, 0.0) == 1.0  # a run of one time still renders [0, 1]
    for bad in (float("nan"), float("inf"), -0.1):
        with pytest.raises(ValueError, match="--t-end must be a finite time"):
            check_time(bad, 0.75, "--t-end")


@pytest.mark.parametrize("preset", list(PRESETS))
def test_every_preset_is_valid(preset):
    assert validate(PRESETS[preset]()) is not None


def test_the_tiny_preset_caps_its_gaussians():
    cfg = PRESETS["tiny"]()
    assert cfg.densify.refine_every == 1 and cfg.densify.max_gaussians <= 20_000


def test_train_writes_its_summary_to_json_stores_absolute_paths_and_resumes(tmp_path, capsys, monkeypatch):
    import json

    write_tiny_scene(tmp_path / "scene", size=16)
    monkeypatch.chdir(tmp_path)
    argv = ["train", "--data", "scene", "--run", "run", "--preset", "tiny", "--device", "cpu"]
    main([*argv, "--json", "summary.json"])
    printed = capsys.readouterr().out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary == json.loads(printed[printed.index("{") :])
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    assert saved["data"] == str(tmp_path / "scene") and saved["run"] == str(tmp_path / "run")
    monkeypatch.chdir(tmp_path / "scene")  # --resume reads the run's own config from anywhere
    main(
        [
            "train",
            "--resume",
            str(tmp_path / "run"),
            "--device",
            "cpu",
            "--json",
            str(tmp_path / "again.json"),
        ]
    )
    again = json.loads((tmp_path / "again.json").read_text())
    assert again["iterations"] == summary["iterations"] and again["preset"] == "tiny"
