"""A batch of views per step (``stage2.views_per_step``): the fields are evaluated once for the step's
time and several cameras of that time are rendered; the loss is the mean over them."""

import dataclasses
import json

import pytest
import torch
from tests.conftest import write_tiny_scene

from tracegs.config import make_config
from tracegs.train.optim import zero_grads
from tracegs.train.trainer import Trainer


def _trainer(scene, run, views_per_step: int, **settings) -> Trainer:
    cfg = make_config(
        "tiny", data=scene, run=run, device="cpu", static_iterations=2, dynamic_iterations=3, **settings
    )
    cfg.init_points, cfg.bf16 = 300, False  # fp32 fields: the sums compare to float rounding
    cfg.stage2 = dataclasses.replace(cfg.stage2, views_per_step=views_per_step, skip_static=False)
    return Trainer(cfg, progress=False)


def _gradients(trainer: Trainer, views, t_prime: float) -> dict[str, torch.Tensor]:
    """The gradients of every parameter (Gaussians and fields) of the loss of ``views`` rendered at
    their time from Gaussians carried there from ``t_prime``."""
    zero_grads(trainer.state.all_optimizers())
    state, _ = trainer.model.training_state(t_prime, views[0].time)
    losses, _ = trainer.views_loss(state, views, trainer.data.background)
    losses["loss"].backward()
    return {
        name: p.grad.clone() if p.grad is not None else torch.zeros_like(p)
        for name, p in trainer.model.named_parameters()
    }


def test_a_batch_of_views_has_the_mean_gradient_of_its_single_views(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path / "run", views_per_step=3)
    trainer.model.begin_dynamic_stage()
    # fields that move things (their heads start at zero, where most gradients vanish)
    torch.manual_seed(1)
    with torch.no_grad():
        for p in trainer.model.field_parameters():
            p.add_(0.05 * torch.randn_like(p))
    index = next(i for i, v in enumerate(trainer.data.views) if v.time > 0)
    views = trainer.sampler.views_at_time(index)
    assert len(views) == 3 and len({v.camera_id for v in views}) == 3
    assert {v.time for v in views} == {views[0].time}
    t_prime = 0.0
    batched = _gradients(trainer, views, t_prime)
    singles = [_gradients(trainer, [v], t_prime) for v in views]
    fields = {name for name, _ in trainer.model.named_parameters() if not name.startswith("gaussians")}
    assert any(batched[name].abs().max() > 0 for name in fields)  # the fields are part of the test
    for name, grad in batched.items():
        mean = sum(s[name] for s in singles) / len(views)
        assert torch.allclose(grad, mean, rtol=1e-4, atol=1e-8), name


def test_views_of_a_time_are_other_cameras_and_fewer_where_fewer_saw_it(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path / "run", views_per_step=5)
    for index, view in enumerate(trainer.data.views):
        views = trainer.sampler.views_at_time(index)
        assert views[0] is view
        assert len(views) == 3  # the tiny scene's 3 training cameras per time
        assert {v.time for v in views} == {view.time}
    one = _trainer(tiny_scene, tmp_path / "one", views_per_step=1)
    assert [v.name for v in one.sampler.views_at_time(2)] == [one.data.views[2].name]


def test_training_with_a_batch_of_views_counts_each_view_for_densification(tiny_scene, tmp_path):
    trainer = _trainer(tiny_scene, tmp_path / "run", views_per_step=2)
    trainer.cfg.densify = dataclasses.replace(trainer.cfg.densify, refine_start=100, reset_every=0)
    trainer.strategy = type(trainer.strategy)(trainer.cfg.densify, trainer.extent, 100)
    while trainer.state.step < trainer.cfg.static_iterations:
        trainer.train_step()
    trainer.state.strategy = trainer.strategy.initialize_state()
    trainer.train_step()  # one dynamic step, two views: every Gaussian is counted at most twice
    counts = trainer.state.strategy["count"]
    assert counts.max() == 2 and counts.min() >= 0
    summary = _trainer(tiny_scene, tmp_path / "full", views_per_step=2).train()
    log = [json.loads(line) for line in (tmp_path / "full" / "log.jsonl").read_text().splitlines()]
    assert summary["iterations"] == 5 and all(torch.isfinite(torch.tensor(r["loss"])) for r in log)


@pytest.mark.parametrize("bad", [0, -1])
def test_views_per_step_must_be_positive(tiny_scene, tmp_path, bad):
    with pytest.raises(ValueError, match="views-per-step"):
        _trainer(tiny_scene, tmp_path / "run", views_per_step=bad)


def test_a_monocular_video_gets_one_view_a_step_and_as_many_more_steps(tmp_path):
    mono = write_tiny_scene(tmp_path / "mono", n_cams=2)  # one training camera per time
    trainer = _trainer(mono, tmp_path / "run", views_per_step=4)
    assert trainer.sampler.views_per_step == 1
    assert trainer.dynamic_steps == 4 * 3 and trainer.total_steps == 2 + 12
    multi = _trainer(write_tiny_scene(tmp_path / "multi"), tmp_path / "run2", views_per_step=4)
    assert multi.sampler.views_per_step == 3 and multi.dynamic_steps == 4  # ceil(3 x 4 / 3)
