"""``TrainState``: what changes as a run trains, saved whole in the checkpoint and read back equal, from
the checkpoints of this version and of earlier ones."""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import torch
from tests.conftest import write_tiny_scene

from tracegs.config import make_config
from tracegs.run import CHECKPOINT, load_config, load_tensors
from tracegs.train.checkpoint import checkpoint, restore
from tracegs.train.state import TrainState
from tracegs.train.trainer import Trainer

FIXTURE = Path(__file__).parents[1] / "fixtures" / "run_1668a0e"  # a run of an earlier version


def assert_same(a, b, key: str = "") -> None:
    """``a`` and ``b`` (nested dicts, lists, tensors, plain values) hold the same keys and values."""
    assert type(a) is type(b), key
    if isinstance(a, dict):
        assert a.keys() == b.keys(), key
        for k in a:
            assert_same(a[k], b[k], f"{key}.{k}")
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), key
        for i, (u, v) in enumerate(zip(a, b, strict=True)):
            assert_same(u, v, f"{key}.{i}")
    elif isinstance(a, torch.Tensor):
        assert a.dtype == b.dtype and torch.equal(a, b), key
    else:
        assert a == b, key


def test_the_train_state_round_trips_through_the_checkpoint(tiny_scene, tmp_path):
    cfg = make_config(
        "tiny",
        data=tiny_scene,
        run=tmp_path / "run",
        device="cpu",
        init_points=150,
        static_iterations=2,
        dynamic_iterations=6,
        **{"densify.refine_every": 4, "densify.refine_stop": 100, "densify.refine_stop_fraction": 1.0},
    )
    trainer = Trainer(cfg, progress=False)
    for _ in range(3):  # into stage 2, between two refinements: densification statistics held
        trainer.train_step()
    state = trainer.state
    state.lr_scale, state.restorations = 0.5, [{"step": 2, "to_step": 1, "what": "loss"}]
    state.static_fraction = None
    assert state.strategy["grad2d"] is not None and state.field_opt.state
    trainer.save()

    saved = load_tensors(cfg.run / CHECKPOINT)
    for key in ("model", "step", "train_seconds", "t_max", "static_mask"):  # what ``run.py`` reads
        assert key in saved
    assert saved["step"] == 3 and saved["lr_scale"] == 0.5
    resumed = Trainer(cfg, progress=False)
    assert isinstance(resumed.state, TrainState) and resumed.state is not state
    assert_same(resumed.state.state_dict(resumed.device), state.state_dict(trainer.device))
    for field in dataclasses.fields(TrainState):
        if field.name not in ("optimizers", "field_opt", "colour_opt", "generator"):  # (compared above)
            assert_same(getattr(resumed.state, field.name), getattr(state, field.name), field.name)
    assert_same(resumed.model.state_dict(), trainer.model.state_dict())
    # and the parameters the restored optimisers step are the model's own
    for name, opt in resumed.state.optimizers.items():
        assert opt.param_groups[0]["params"][0] is resumed.model.gaussians[name]


def test_restore_gives_the_saved_state_in_memory(tiny_scene, tmp_path):
    """``checkpoint`` then ``restore``, without a file: the same state and model."""
    cfg = make_config("tiny", data=tiny_scene, run=tmp_path / "run", device="cpu", init_points=80)
    trainer = Trainer(cfg, progress=False)
    trainer.train_step()
    saved = checkpoint(trainer.state, trainer.model, cfg, trainer.fingerprint, trainer.t_max, trainer.device)
    expected = trainer.state.state_dict(trainer.device)
    other = Trainer(dataclasses.replace(cfg, run=tmp_path / "other", seed=1), progress=False)
    state = restore(
        saved, other.model, cfg.optim, other.extent, other.strategy, other.state.generator, other.device
    )
    assert_same(state.state_dict(other.device), expected)
    assert_same(other.model.state_dict(), trainer.model.state_dict())


def test_a_run_folder_of_an_earlier_version_resumes(tmp_path):
    """The fixture's checkpoint (an earlier layout, its optimiser states dropped) resumes: it holds
    the finished run's step, and training it again calibrates and saves it in today's layout."""
    scene = write_tiny_scene(tmp_path / "scene")
    run = shutil.copytree(FIXTURE, tmp_path / "run")
    cfg = dataclasses.replace(load_config(run / "config.json"), data=scene, run=run)
    trainer = Trainer(cfg, progress=False)
    assert trainer.state.step == cfg.total_iterations == load_tensors(FIXTURE / CHECKPOINT)["step"]
    summary = trainer.train()
    assert summary["iterations"] == cfg.total_iterations
    saved = load_tensors(run / CHECKPOINT)
    assert saved["lr_scale"] == 1.0 and saved["step"] == cfg.total_iterations
    old = load_tensors(FIXTURE / CHECKPOINT)["model"]
    assert all(torch.equal(saved["model"][k], v) for k, v in old.items())
