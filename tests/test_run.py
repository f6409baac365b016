"""The run folder (``tracegs.run``): safe loading, no side effects, and run folders of earlier versions."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import pytest
import torch

from tests.conftest import write_tiny_scene
from tracegs.config import make_config
from tracegs.export.render import render_command
from tracegs.run import (
    CHECKPOINT,
    EXTRAPOLATION,
    RunError,
    calibrate_run,
    load_config,
    load_run,
    load_tensors,
    truncate_log,
)
from tracegs.run_compat import migrate_config
from tracegs.train.trainer import Trainer

FIXTURE = Path(__file__).parent / "fixtures" / "run_1668a0e"


class _Payload:
    """Unpickling this runs ``os.system``: what a malicious checkpoint would do."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_a_planted_pickle_in_a_checkpoint_is_refused_without_running_it(tmp_path):
    run = tmp_path / "run"
    shutil.copytree(FIXTURE, run)
    marker = tmp_path / "executed"
    ckpt = torch.load(run / CHECKPOINT, weights_only=True)
    ckpt["extra"] = _Payload(marker)
    torch.save(ckpt, run / CHECKPOINT)
    with pytest.raises(RunError, match="refused") as err:
        load_run(run, device="cpu")
    assert str(run / CHECKPOINT) in str(err.value)
    assert "system" in str(err.value)  # (the global it would have called, as the unpickler names it)
    assert not marker.exists()


def test_a_run_folder_written_before_the_run_module_still_renders(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene")
    run = tmp_path / "run"
    shutil.copytree(FIXTURE, run)
    cfg = load_config(run / "config.json")
    old = json.loads((FIXTURE / "config.json").read_text())["dynamic"]
    assert cfg.stage2.dt_frames == old["dt_frames"] and cfg.stage2.skip_static == (old["skip_static"] > 0)
    assert cfg.extrapolation.handover_frames == old["handover_frames"]
    assert cfg.extrapolation.free_bodies == old["free_bodies"]
    loaded = load_run(run, device="cpu")
    old_ckpt = torch.load(FIXTURE / CHECKPOINT, weights_only=True)
    assert loaded.state.freeze_threshold == old_ckpt["freeze_threshold"]
    assert torch.equal(loaded.state.unseen, old_ckpt["unseen_mask"])
    image = render_command(run, tmp_path / "t1.png", time=1.2, camera="test:0", data=scene, device="cpu")
    assert image.is_file()


def test_a_run_without_its_post_training_state_names_the_command_that_makes_it(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene")
    run = tmp_path / "run"
    shutil.copytree(FIXTURE, run)
    ckpt = torch.load(run / CHECKPOINT, weights_only=True)
    del ckpt["unseen_mask"]  # as a checkpoint written before training ended
    torch.save(ckpt, run / CHECKPOINT)
    with pytest.raises(RunError, match=f"tracegs calibrate --run {run}"):
        load_run(run, device="cpu")
    (run / "summary.json").write_text(json.dumps({"iterations": 7, "freeze_threshold": -1.0}))
    state = calibrate_run(run, device="cpu", data=scene)
    assert (run / EXTRAPOLATION).is_file()
    reloaded = load_run(run, device="cpu").state
    assert reloaded.freeze_threshold == state.freeze_threshold
    assert torch.equal(reloaded.unseen, state.unseen)
    summary = json.loads((run / "summary.json").read_text())  # the summary says what was chosen now
    assert summary["iterations"] == 7 and summary["freeze_threshold"] == state.freeze_threshold
    assert summary["joint_laws"] == state.report.get("joint_laws", [])


def test_loading_a_run_writes_nothing_and_gives_the_state_training_chose(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene")
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu")
    trainer = Trainer(cfg, progress=False)
    trainer.train()
    before = {p.name: p.stat().st_mtime_ns for p in cfg.run.iterdir()}
    loaded = load_run(cfg.run, device="cpu")
    assert {p.name: p.stat().st_mtime_ns for p in cfg.run.iterdir()} == before
    chosen = trainer.extrapolation
    assert loaded.state.freeze_threshold == chosen.freeze_threshold
    assert torch.equal(loaded.state.unseen, chosen.unseen)
    assert (loaded.state.free_bodies is None) == (chosen.free_bodies is None)
    assert set(load_tensors(cfg.run / CHECKPOINT)) >= {"model", "step", "t_max", "static_mask"}


def test_an_old_config_with_a_removed_setting_in_use_is_refused_by_name():
    data = json.loads((FIXTURE / "config.json").read_text())
    data["dynamic"]["rotation_consistency"] = 0.5
    with pytest.raises(ValueError, match="rotation_consistency"):
        migrate_config(data)


def test_a_run_stores_absolute_paths_and_is_evaluated_from_another_folder(tmp_path, monkeypatch):
    from tracegs.eval.protocol import evaluate_run

    monkeypatch.chdir(tmp_path)
    write_tiny_scene(Path("scene"))
    cfg = make_config("tiny", data=Path("scene"), run=Path("runs/a"), device="cpu")
    Trainer(cfg, progress=False).train()
    saved = load_config(tmp_path / "runs" / "a" / "config.json")
    assert saved.data == tmp_path / "scene" and saved.run == tmp_path / "runs" / "a"
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    report = evaluate_run(tmp_path / "runs" / "a", with_lpips=False, save_images=False, device="cpu")
    assert report  # read the scene from where the run says it is


def test_truncate_log_keeps_the_lines_up_to_the_step(tmp_path):
    path = tmp_path / "log.jsonl"
    lines = [json.dumps({"step": s, "loss": 1.0 / s}) for s in (1, 2, 3, 4)]
    path.write_text("\n".join(lines) + '\n{"step": 5, "lo')  # a line cut by a kill
    truncate_log(path, 2)
    assert path.read_text() == "\n".join(lines[:2]) + "\n"
    truncate_log(path, 0)
    assert path.read_text() == ""
    truncate_log(tmp_path / "none.jsonl", 3)  # no log yet: nothing to do
    assert not (tmp_path / "none.jsonl").exists()


def test_calibrate_switches_the_surface_painters_rule_of_a_trained_run(tmp_path):
    from tracegs.cli import main

    scene = write_tiny_scene(tmp_path / "scene")
    run = tmp_path / "run"
    shutil.copytree(FIXTURE, run)
    assert load_run(run, device="cpu").config.extrapolation.surface_painters == "edge"  # the default
    args = ["calibrate", "--run", str(run), "--data", str(scene), "--surface-painters", "hold"]
    main([*args, "--device", "cpu"])
    assert json.loads((run / "config.json").read_text())["extrapolation"]["surface_painters"] == "hold"
    assert load_run(run, device="cpu").config.extrapolation.surface_painters == "hold"
