"""Training end to end on a tiny generated scene: every preset, method and ablation switch, on CPU."""

import dataclasses
import json

import pytest
import torch

from tracegs.config import PRESETS, apply_overrides, make_config
from tracegs.train.trainer import Trainer, load_run


def _cfg(scene, run, preset="tiny", **kw):
    cfg = make_config(preset, data=scene, run=run, device="cpu", static_iterations=2, dynamic_iterations=2)
    cfg.init_points = 300
    cfg.checkpoint_every = 1
    cfg.densify = dataclasses.replace(cfg.densify, refine_start=0, refine_every=1, reset_every=0)
    return apply_overrides(cfg, kw)


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_trains_two_iterations(tiny_scene, tmp_path, preset):
    summary = Trainer(_cfg(tiny_scene, tmp_path / "run", preset), progress=False).train()
    assert summary["iterations"] == 4
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in log)


ABLATIONS = [
    {"method": "defgs"},
    {"method": "static"},
    {"dynamics__order": 1},
    {"dynamics__order": 3},
    {"dynamic__dt_frames": 1.0},
    {"dynamic__dt_frames": 3.0},
    {"dynamic__use_deformation": False},
    {"dynamic__physics_derivation": False},
    {"dynamics__equivalent": False},
    {"dynamic__integrator": "rk2_paper"},
    {"dynamic__integrator": "rk4"},
    {"deformation__kind": "hexplane"},
    {"bf16": True},
]


@pytest.mark.parametrize("switch", ABLATIONS, ids=lambda d: ",".join(f"{k}={v}" for k, v in d.items()))
def test_every_ablation_switch_trains_and_renders_the_future(tiny_scene, tmp_path, switch):
    cfg = _cfg(tiny_scene, tmp_path / "run", **switch)
    Trainer(cfg, progress=False).train()
    model, loaded, meta = load_run(tmp_path / "run", device="cpu")
    assert loaded == cfg
    for t in (0.5, 1.2):
        state = model.state_at(t, meta["t_max"])
        assert torch.isfinite(state["means"]).all() and torch.isfinite(state["quats"]).all()


def test_resume_continues_from_checkpoint(tiny_scene, tmp_path):
    cfg = _cfg(tiny_scene, tmp_path / "run")
    trainer = Trainer(cfg, progress=False)
    for _ in range(3):
        trainer.train_step()
    trainer.save()
    resumed = Trainer(cfg, progress=False)
    assert resumed.step == 3
    for name in ("means", "sh0"):
        assert torch.equal(resumed.model.gaussians[name], trainer.model.gaussians[name])
    assert resumed.train()["iterations"] == 4


def test_straight_through_gradient_reaches_deformation_field(tiny_scene, tmp_path):
    trainer = Trainer(_cfg(tiny_scene, tmp_path / "run"), progress=False)
    model = trainer.model
    # give the fields a non-zero output so that gradients are not trivially blocked
    with torch.no_grad():
        for p in model.field_parameters():
            p.add_(0.01 * torch.randn_like(p))
    state = model.training_state(0.25, 0.5)
    state["means"].sum().backward()
    grads = [p.grad for p in model.deformation.parameters()]
    assert any(g is not None and g.abs().sum() > 0 for g in grads)
    # the rendered value is the physics result, not f_defo(t)
    with torch.no_grad():
        target = model.deform(0.5)["means"]
    assert not torch.allclose(state["means"].detach(), target)


def test_new_model_is_no_motion(tiny_scene, tmp_path):
    """New fields: f_defo is exactly the identity; f_trd has zero velocities and (order 2) only tiny
    random accelerations (they must start non-zero to learn, see models/dynamics.py)."""
    for order, tol in ((1, 1e-7), (2, 1e-4)):
        trainer = Trainer(_cfg(tiny_scene, tmp_path / f"run{order}", dynamics__order=order), progress=False)
        model, g = trainer.model, trainer.model.gaussians
        assert torch.equal(model.deform(0.3)["means"], g["means"])
        for t in (0.0, 0.3, 1.4):
            state = model.state_at(t, t_max=0.5)
            assert torch.allclose(state["means"], g["means"], atol=tol)
            assert torch.allclose(state["scales"], g["scales"])
