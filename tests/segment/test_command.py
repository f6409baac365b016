"""`tracegs segment` end to end on a tiny trained run of a synthetic scene: labels in the run folder,
masks, PLY and video written, scores where the scene has ground truth, clear errors otherwise."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from plyfile import PlyData

from tracegs.cli import main
from tracegs.config import make_config
from tracegs.data.cameras import scene_extent_from_cameras
from tracegs.data.scene import load_scene
from tracegs.data.synth import synthesize
from tracegs.segment import SegmentConfig, SegmentError, load_segments, segment_run
from tracegs.train.trainer import Trainer


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("seg")
    scene = synthesize("fan", root / "scene", resolution=24, views=4, frames=8, progress=False, spp=1)
    cfg = make_config(
        "tiny", data=scene, run=root / "run", device="cpu", init_points=300, **{"stage2.skip_static": False}
    )
    Trainer(cfg, progress=False).train()
    return scene, root / "run"


def test_segment_writes_labels_masks_ply_and_scores(trained, tmp_path):
    scene, run = trained
    moving = SegmentConfig(static_displacement=1e-9)  # a tiny run hardly moves anything
    report = segment_run(
        run, k=2, out=tmp_path / "out", json_path=tmp_path / "r.json", video=True, settings=moving
    )
    stored = load_segments(run)
    n = len(stored["labels"])
    assert stored["k"] == report["k"] == 2 and int(stored["labels"].max()) <= 1
    assert sum(s["gaussians"] for s in report["segments"]) == n
    assert json.loads((tmp_path / "r.json").read_text())["k"] == 2
    assert (tmp_path / "out" / "segment.json").is_file()
    ply = PlyData.read(report["outputs"]["ply"])
    assert len(ply["vertex"]) == n and "f_dc_0" in ply["vertex"].data.dtype.names
    assert (tmp_path / "out" / report["outputs"]["masks"].split("/")[-1]).is_file()
    assert report["outputs"]["video"].endswith((".mp4", ".gif"))
    scores = report["scores"]
    assert set(scores["splits"]) == {"train", "val", "test"}
    assert scores["training_times"]["images"] + scores["future_times"]["images"] == sum(
        s["images"] for s in scores["splits"].values()
    )
    assert scores["future_times"]["images"] > 0
    for row in scores["per_time"]:
        assert all(0.0 <= row[m] <= 1.0 for m in ("ap", "pq", "f1", "precision", "recall", "miou"))
    assert report["ground_truth"]["layout"] == "parts"


def test_auto_k_flow_features_and_a_future_time(trained, tmp_path):
    _, run = trained
    report = segment_run(run, auto_k=True, time_=1.0, out=tmp_path, settings=SegmentConfig(features="flow"))
    assert report["auto_k"]["criterion"] == "rigid residual"
    assert report["k"] in [row["k"] for row in report["auto_k"]["tried"]] or report["k"] == 1
    assert load_segments(run, "flow")["k"] == report["k"]
    assert report["outputs"]["masks"].endswith("masks_t1.000.png")


def test_the_cli_and_its_errors(trained, tmp_path, capsys):
    _, run = trained
    main(["segment", "--run", str(run), "--k", "2", "--out", str(tmp_path), "--no-score",
          "--settings.static-displacement", "1e-9"])  # fmt: skip
    assert "K = 2" in capsys.readouterr().out
    main(["segment", "--run", str(run), "--k", "3", "--out", str(tmp_path), "--no-score",
          "--settings.static-displacement", "10"])  # fmt: skip
    assert "asked for K = 3, made 1" in capsys.readouterr().out
    with pytest.raises(ValueError, match="--k K or --auto-k"):
        segment_run(run)
    with pytest.raises(ValueError, match="not both"):
        segment_run(run, k=2, auto_k=True)
    with pytest.raises(FileNotFoundError, match="config.json"):
        segment_run(tmp_path / "nowhere", k=2)


def test_a_defgs_run_needs_flow_features(tmp_path):
    scene = synthesize("slider", tmp_path / "scene", resolution=16, views=3, frames=6, progress=False, spp=1)
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu", init_points=200, method="defgs")
    Trainer(cfg, progress=False).train()
    with pytest.raises(SegmentError, match="features flow"):
        segment_run(tmp_path / "run", k=2, score=False)
    report = segment_run(tmp_path / "run", k=3, score=False, settings=SegmentConfig(features="flow"))
    assert report["k"] <= 3 and np.isfinite(report["static_threshold"])


def test_ignore_pixels_reaches_the_scores(trained, tmp_path):
    """`--ignore-pixels` leaves the smaller ground-truth segments out of the scores (OGC's rule): past
    the image's size, every one of them, so nothing is left to recall."""
    _, run = trained
    scores = {}
    for ignore in (0, 24 * 24 + 1):
        main(["segment", "--run", str(run), "--k", "2", "--out", str(tmp_path / str(ignore)),
              "--json", str(tmp_path / f"{ignore}.json"), "--ignore-pixels", str(ignore),
              "--settings.static-displacement", "1e-9"])  # fmt: skip
        scores[ignore] = json.loads((tmp_path / f"{ignore}.json").read_text())["scores"]["training_times"]
    assert scores[0]["recall"] > 0 and np.isfinite(scores[0]["miou"])
    assert scores[24 * 24 + 1]["recall"] == 0 and np.isnan(scores[24 * 24 + 1]["miou"])


def test_the_default_static_threshold_is_the_one_training_marks_with(trained, tmp_path, monkeypatch):
    """Without a freeze threshold from the calibration, the static group is what f_defo moves less
    than ``stage2.static_displacement`` times the scene extent (its unit), as training marks it."""
    from tracegs.segment import command

    scene, run = trained
    real = command.load_run

    def no_freeze(*args, **kwargs):
        loaded = real(*args, **kwargs)
        loaded.state.freeze_threshold = 0.0
        return loaded

    monkeypatch.setattr(command, "load_run", no_freeze)
    report = segment_run(run, k=2, score=False, out=tmp_path / "seg")
    centers = torch.stack([f.camera.center for f in load_scene(scene, "train").frames])
    extent = scene_extent_from_cameras(centers)
    assert extent > 2
    assert report["static_threshold"] == pytest.approx(
        real(run, "cpu").config.stage2.static_displacement * extent
    )
