"""What the `capture` preset adds for a real rig: per-camera colours trained and read back with the
run, the surroundings held still outside the region the foreground masks sweep, a near plane."""

from __future__ import annotations

import torch
from tests.train.test_init import capture  # noqa: F401  (the fixture: a generated scene with masks)

from tracegs.config import make_config
from tracegs.data.hull import in_any_hull
from tracegs.run import load_run
from tracegs.train.trainer import Trainer


def test_camera_colours_train_and_come_back_with_the_run(capture, tmp_path):  # noqa: F811
    cfg = make_config("tiny", data=capture, run=tmp_path / "run", init_points=50, camera_colour=True)
    cfg.static_iterations, cfg.dynamic_iterations, cfg.optim.colour_lr = 5, 5, 0.05
    trainer = Trainer(cfg, progress=False)
    ids = sorted({v.camera_id for v in trainer.data.views})
    assert trainer.model.camera_colour.camera_ids.tolist() == ids and len(ids) > 1
    trainer.train()
    run = load_run(tmp_path / "run", "cpu")
    colour = run.model.camera_colour
    assert colour.camera_ids.tolist() == ids and float(colour.log_gain.detach().abs().max()) > 0
    assert torch.equal(colour.offset, trainer.model.camera_colour.offset.detach())
    image = torch.rand(4, 4, 3)
    mean = image * colour.log_gain.mean(0).exp() + colour.offset.mean(0)
    assert torch.allclose(run.model.colour(image, 10_000), mean)  # a camera never trained: the mean map


def test_outside_the_swept_region_the_gaussians_stand_still(capture, tmp_path):  # noqa: F811
    cfg = make_config("capture", data=capture, run=tmp_path / "run", init_points=300)
    cfg.static_iterations = cfg.densify.refine_stop = 3
    cfg.dynamic_iterations, cfg.init_surroundings, cfg.hull_resolution = 2, 500, 32
    cfg.densify.refine_start, cfg.densify.refine_every = 0, 1
    trainer = Trainer(cfg, progress=False)
    for _ in range(cfg.static_iterations + 1):
        trainer.train_step()
    mask = trainer.model.static_mask
    means = trainer.model.gaussians["means"].detach()
    frames = [f for f in trainer.data.scene.frames if f.time <= trainer.t_max]
    inside = in_any_hull(capture, frames, means)
    assert mask is not None and bool(inside.any()) and bool(mask.any())
    assert not bool((mask & inside).any())  # nothing inside the region the ball sweeps stands still
    assert trainer.state.static_fraction == float(mask.float().mean())


def test_the_near_plane_leaves_out_what_is_nearer(capture, tmp_path):  # noqa: F811
    cfg = make_config("tiny", data=capture, run=tmp_path / "run", init_points=50)
    model = Trainer(cfg, progress=False).model
    g = model.gaussians
    state = {"means": g["means"], "quats": g["quats"], "scales": g["scales"]}
    from tracegs.data.scene import load_scene

    camera = load_scene(capture, "train").frames[0].camera
    depth = (g["means"].detach() @ camera.viewmat[:3, :3].T + camera.viewmat[:3, 3])[:, 2]
    with torch.no_grad():
        near = model.render(state, camera, 0, torch.zeros(3)).image
        model.set_near_plane(float(depth.max()) + 1.0)  # beyond every Gaussian: nothing drawn
        far = model.render(state, camera, 0, torch.zeros(3)).image
    assert float(near.abs().sum()) > 0 and float(far.abs().sum()) == 0


def test_the_mask_loss_reaches_only_the_gaussians_that_move(capture, tmp_path):  # noqa: F811
    cfg = make_config("capture", data=capture, run=tmp_path / "run", init_points=300)
    cfg.static_iterations = cfg.densify.refine_stop = 1
    cfg.dynamic_iterations, cfg.init_surroundings, cfg.hull_resolution = 2, 500, 32
    cfg.optim.mask_weight = 1.0
    trainer = Trainer(cfg, progress=False)
    trainer.train_step()
    trainer.train_step()  # the first step of stage 2 marks what stands still
    moving = trainer.model.moving_rows
    assert moving is not None and 0 < len(moving) < len(trainer.model.static_mask)
    view = trainer.data[0]
    state, _ = trainer.model.training_state(view.time, view.time)
    losses, _ = trainer.views_loss(state, [view], trainer.data.background)
    opacities = trainer.model.gaussians["opacities"]
    (grad,) = torch.autograd.grad(losses["mask"], opacities)
    assert float(losses["mask"].detach()) > 0 and float(grad[moving].abs().sum()) > 0
    assert float(grad[trainer.model.static_mask].abs().sum()) == 0


def test_frozen_surroundings_take_no_step_in_stage_2(capture, tmp_path):  # noqa: F811
    cfg = make_config("capture", data=capture, run=tmp_path / "run", init_points=300)
    cfg.static_iterations = cfg.densify.refine_stop = 3
    cfg.dynamic_iterations, cfg.init_surroundings, cfg.hull_resolution = 4, 500, 32
    assert cfg.stage2.freeze_surroundings
    trainer = Trainer(cfg, progress=False)
    for _ in range(cfg.static_iterations + 1):  # stage 1, then the step that marks the surroundings
        trainer.train_step()
    mask = trainer.model.static_mask
    before = {k: v.detach().clone() for k, v in trainer.model.gaussians.items()}
    for _ in range(3):
        trainer.train_step()
    after = trainer.model.gaussians
    assert all(torch.equal(after[k][mask], before[k][mask]) for k in before)
    assert not torch.equal(after["means"][~mask], before["means"][~mask])  # the subject still learns


def test_stage_2_densifies_what_moves_and_leaves_the_surroundings(capture, tmp_path):  # noqa: F811
    cfg = make_config("capture", data=capture, run=tmp_path / "run", init_points=300)
    cfg.static_iterations = cfg.densify.refine_stop = 3
    cfg.dynamic_iterations, cfg.init_surroundings, cfg.hull_resolution = 6, 500, 32
    cfg.densify.refine_every, cfg.densify.grow_grad2d, cfg.densify.moving_refine_stop = 2, 1e-12, 8
    trainer = Trainer(cfg, progress=False)
    for _ in range(cfg.static_iterations + 1):  # stage 1, then the step that marks the surroundings
        trainer.train_step()
    held = trainer.model.static_mask.clone()
    surroundings = {k: v.detach()[held].clone() for k, v in trainer.model.gaussians.items()}
    moving = int((~held).sum())
    for _ in range(4):
        trainer.train_step()
    mask = trainer.model.static_mask
    assert mask.shape[0] == trainer.model.gaussians["means"].shape[0] and int((~mask).sum()) > moving
    assert all(torch.equal(trainer.model.gaussians[k].detach()[mask], v) for k, v in surroundings.items())
    trainer.train()  # the run goes on to its end (rows changed mid-stage) and saves
    run = load_run(tmp_path / "run", "cpu")
    assert torch.equal(run.model.static_mask, trainer.model.static_mask)
