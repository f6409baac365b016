"""Training end to end on a tiny generated scene: every preset, method and ablation switch, on CPU."""

import dataclasses
import json
import math

import pytest
import torch

import tracegs
from tracegs.config import PRESETS, apply_overrides, make_config
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.run import load_run
from tracegs.train.trainer import Trainer


def _cfg(scene, run, preset="tiny", settings: dict | None = None, **kw):
    """The tiny run's config with top-level fields ``kw`` and dotted ``settings`` (``stage2.dt_frames``)."""
    cfg = make_config(preset, data=scene, run=run, device="cpu", static_iterations=2, dynamic_iterations=2)
    cfg.init_points = 300
    cfg.checkpoint_every = 1
    cfg.densify = dataclasses.replace(cfg.densify, refine_start=0, refine_every=1, reset_every=0)
    return apply_overrides(cfg, {**kw, **(settings or {})})


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_every_preset_trains_two_iterations(tiny_scene, tmp_path, preset):
    summary = Trainer(_cfg(tiny_scene, tmp_path / "run", preset), progress=False).train()
    assert summary["iterations"] == 4
    assert summary["device"] == "cpu" and summary["rasteriser"] in ("native", "reference")
    log = [json.loads(line) for line in (tmp_path / "run" / "log.jsonl").read_text().splitlines()]
    assert all(torch.isfinite(torch.tensor(r["loss"])) for r in log)


ABLATIONS = [
    {"method": "defgs"},
    {"method": "static"},
    {"dynamics.order": 1},
    {"dynamics.order": 3},
    {"stage2.dt_frames": 1.0},
    {"stage2.dt_frames": 3.0},
    {"stage2.use_deformation": False},
    {"stage2.physics_derivation": False},
    {"dynamics.equivalent": False},
    {"stage2.integrator": "rk2_paper"},
    {"stage2.integrator": "rk4"},
    {"deformation.kind": "hexplane"},
    {"bf16": True},
    {"stage2.acceleration_consistency": 0.0, "dynamics.detach_acceleration_features": False},
    {"dynamics.acceleration_depth": 0, "dynamics.detach_acceleration_features": True},
    {"dynamics.angular_accelerations_from_head": False, "dynamics.detach_acceleration_features": False},
    {"stage2.skip_static": False},
    {"stage2.consistency_frames": 0.0},
    {"stage2.skip_static": True, "stage2.static_displacement": 0.5},
    {"method": "defgs", "stage2.skip_static": True, "stage2.static_displacement": 0.5},
]


@pytest.mark.parametrize("switch", ABLATIONS, ids=lambda d: ",".join(f"{k}={v}" for k, v in d.items()))
def test_every_ablation_switch_trains_and_renders_the_future(tiny_scene, tmp_path, switch):
    cfg = _cfg(tiny_scene, tmp_path / "run", settings=switch)
    Trainer(cfg, progress=False).train()
    run = load_run(tmp_path / "run", device="cpu")
    assert run.config == cfg
    for t in (0.5, 1.2):
        state = run.predictor.gaussians_at(t)
        assert torch.isfinite(state["means"]).all() and torch.isfinite(state["quats"]).all()


@pytest.mark.parametrize(
    "device",
    # on CUDA the checkpoint is loaded onto the GPU, the CPU random state with it
    [
        "cpu",
        pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")),
    ],
)
def test_resume_continues_from_checkpoint(tiny_scene, tmp_path, device):
    cfg = _cfg(tiny_scene, tmp_path / "run", device=device)
    trainer = Trainer(cfg, progress=False)
    for _ in range(3):
        trainer.train_step()
    trainer.save()
    resumed = Trainer(cfg, progress=False)
    assert resumed.state.step == 3
    for name in ("means", "sh0"):
        assert torch.equal(resumed.model.gaussians[name], trainer.model.gaussians[name])
    assert resumed.train()["iterations"] == 4


def test_a_failed_calibration_keeps_the_last_steps(tiny_scene, tmp_path, monkeypatch):
    import tracegs.train.trainer as trainer

    cfg = _cfg(tiny_scene, tmp_path / "run")
    cfg.checkpoint_every = 3  # the last checkpoint of the loop would be step 3 of 4

    def broken(*args, **kwargs):
        raise OSError("scene gone")

    monkeypatch.setattr(trainer, "calibrate", broken)
    with pytest.raises(OSError, match="scene gone"):
        Trainer(cfg, progress=False).train()
    monkeypatch.undo()
    resumed = Trainer(cfg, progress=False)
    assert resumed.state.step == cfg.total_iterations
    assert resumed.train()["iterations"] == cfg.total_iterations  # calibrates and writes the summary
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["tracegs"] == tracegs.__version__ and "cores" in summary["machine"]


def test_resume_refuses_a_checkpoint_trained_with_other_settings(tiny_scene, tmp_path):
    cfg = _cfg(tiny_scene, tmp_path / "run")
    trainer = Trainer(cfg, progress=False)
    trainer.train_step()
    trainer.save()
    with pytest.raises(ValueError, match=r"checkpoint\.pt.*stage2\.dt_frames"):
        Trainer(apply_overrides(cfg, {"stage2.dt_frames": 3.0}), progress=False)
    # where things are written is not a training setting, nor is the machine's arithmetic (bf16)
    assert (
        Trainer(apply_overrides(cfg, {"checkpoint_every": 7, "log_every": 3}), progress=False).state.step == 1
    )
    assert Trainer(apply_overrides(cfg, {"bf16": not cfg.bf16}), progress=False).state.step == 1
    # a checkpoint from before a setting existed resumes when the setting keeps its default
    ckpt = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    del ckpt["config"]["stage2"]["skip_static"]
    torch.save(ckpt, tmp_path / "run" / "checkpoint.pt")
    assert Trainer(apply_overrides(cfg, {"stage2.skip_static": False}), progress=False).state.step == 1
    with pytest.raises(ValueError, match=r"stage2\.skip_static"):
        Trainer(apply_overrides(cfg, {"stage2.skip_static": True}), progress=False)
    # a checkpoint with a setting this version does not know names the file
    ckpt["config"]["stage2"]["no_such_setting"] = 1
    torch.save(ckpt, tmp_path / "run" / "checkpoint.pt")
    with pytest.raises(ValueError, match=r"checkpoint\.pt: unknown config field .*no_such_setting"):
        Trainer(cfg, progress=False)


def test_a_finished_run_takes_new_render_time_settings_without_retraining(tiny_scene, tmp_path):
    cfg = _cfg(tiny_scene, tmp_path / "run")
    first = Trainer(cfg, progress=False)
    first.train()
    assert first.extrapolation.freeze_threshold is not None  # chosen after training (freeze_static)
    means = first.model.gaussians["means"].clone()
    changed = apply_overrides(
        cfg,
        {
            "extrapolation.handover_frames": 1.0,
            "extrapolation.freeze_static": False,
            "extrapolation.hold_unseen": False,
        },
    )
    again = Trainer(changed, progress=False)
    assert again.state.step == cfg.total_iterations
    assert again.extrapolation is None  # not the old choices
    assert again.train()["iterations"] == cfg.total_iterations
    assert again.extrapolation.freeze_threshold is None and again.extrapolation.unseen is None
    assert torch.equal(again.model.gaussians["means"], means)  # the training is kept as it was
    run = load_run(tmp_path / "run", device="cpu")
    assert run.config.extrapolation.handover_frames == 1.0 and run.state.freeze_threshold is None
    # and back: the calibration is made again with the settings that ask for it
    trainer = Trainer(cfg, progress=False)
    trainer.train()
    assert trainer.extrapolation.freeze_threshold is not None and trainer.extrapolation.unseen is not None


def _perturbed_model(scene, run, settings: dict | None = None):
    model = Trainer(_cfg(scene, run, settings=settings), progress=False).model
    torch.manual_seed(0)
    with torch.no_grad():  # non-zero field outputs, so that gradients are not trivially blocked
        for p in model.field_parameters():
            p.add_(0.01 * torch.randn_like(p))
    return model


def test_straight_through_at_t_prime_is_exact(tiny_scene, tmp_path):
    """The paper's training (Section 3.3): x = x_phys(x_t'.detach()) + (x_t' - x_t'.detach()), so the rendered position
    has the value of the physics result and the gradient of f_defo(t') with Jacobian exactly I."""
    model = _perturbed_model(tiny_scene, tmp_path / "a")
    state = model.training_state(0.25, 0.5)[0]
    weights = torch.randn_like(state["means"])
    params = [model.gaussians["means"], *model.deformation.parameters()]
    got = torch.autograd.grad((state["means"] * weights).sum(), params, allow_unused=True)
    want = torch.autograd.grad((model.deform(0.25)["means"] * weights).sum(), params, allow_unused=True)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=0, atol=0)
    with torch.no_grad():
        start = model.deform(0.25)
        params = model.query_dynamics(start["means"], 0.25)
        from tracegs.physics.integrate import integrate

        physics = integrate(start["means"], start["quats"], params, 0.25, model.dt_max)[0]
    torch.testing.assert_close(state["means"].detach(), physics)


@pytest.mark.parametrize(
    "depth, angular_from_head",
    [(0, False), (2, False), (2, True)],
    ids=["shared head, detached", "own MLP", "own MLP, angular from the head"],
)
def test_acceleration_consistency_trains_only_the_accelerations(
    tiny_scene, tmp_path, depth, angular_from_head
):
    """The step's extra loss is named "acceleration"; it reaches the accelerations' own parameters and
    nothing else (not the velocities, f_defo, the Gaussians): with the shared head and the features'
    gradient stopped, the head's acceleration rows; with ``acceleration_depth``, their own MLP (and,
    with ``angular_accelerations_from_head``, the head's angular rows)."""
    off = _perturbed_model(tiny_scene, tmp_path / "off", {"stage2.acceleration_consistency": 0.0})
    assert off.training_state(0.25, 0.5)[1] == {}
    model = _perturbed_model(
        tiny_scene,
        tmp_path / "on",
        {
            "stage2.acceleration_consistency": 0.5,
            "dynamics.detach_acceleration_features": depth == 0 or angular_from_head,
            "dynamics.acceleration_depth": depth,
            "dynamics.angular_accelerations_from_head": angular_from_head,
        },
    )
    _, losses = model.training_state(0.25, 0.5)
    assert set(losses) == {"acceleration"} and losses["acceleration"] > 0
    losses["acceleration"].backward()
    field = model.dynamics
    assert field.separate_accelerations == (depth > 0)
    if field.separate_accelerations:
        trained = [*field.acceleration_mlp.parameters(), *field.acceleration_head.parameters()]
        assert all(p.grad.abs().sum() > 0 for p in trained)
    rows = torch.zeros(field.head.weight.shape[0], dtype=torch.bool)
    for name in set(field.head_names) & {"acceleration", "angular_acceleration"}:
        rows[field.head_rows(name)] = True
    grad = (
        field.head.weight.grad if field.head.weight.grad is not None else torch.zeros_like(field.head.weight)
    )
    assert grad[rows].abs().sum() > 0 or not rows.any()
    assert grad[~rows].abs().sum() == 0
    others = [*field.mlp.parameters(), *model.deformation.parameters(), *model.gaussians.values()]
    assert all(p.grad is None or p.grad.abs().sum() == 0 for p in others)


def test_acceleration_consistency_reads_the_velocities_again_at_t_check(tiny_scene, tmp_path):
    """With ``t_check`` the loss compares f_trd's velocities at (x_t', t') plus the accelerations' change
    with those f_trd gives where the motion, integrated from t', is at t_check; by default t_check = t."""
    from tracegs.physics.integrate import acceleration_consistency, integrate

    weight = 0.5
    model = _perturbed_model(
        tiny_scene, tmp_path / "on", {"stage2.acceleration_consistency": weight, "stage2.skip_static": False}
    )
    same = model.training_state(0.25, 0.3)[1]["acceleration"]
    torch.testing.assert_close(model.training_state(0.25, 0.3, t_check=0.3)[1]["acceleration"], same)
    got = model.training_state(0.25, 0.3, t_check=0.05)[1]["acceleration"]
    with torch.no_grad():
        start = model.deform(0.25)
        params = model.query_dynamics(start["means"], 0.25)
        x = integrate(start["means"], start["quats"], params, -0.2, model.dt_max)[0]
        want = weight * acceleration_consistency(params, model.query_dynamics(x, 0.05, rates=False), -0.2)
    torch.testing.assert_close(got.detach(), want)
    assert not torch.allclose(got, same)


def test_consistency_time_goes_the_way_of_t_and_turns_back_at_the_limit(tiny_scene, tmp_path):
    trainer = Trainer(
        _cfg(tiny_scene, tmp_path / "run", settings={"stage2.consistency_frames": 3.0}), progress=False
    )
    dt = trainer.dt_frame
    limit = 30 * dt  # consistency_frames = 3: the span is 3 dt
    assert trainer.sampler.consistency_time(3 * dt, 4 * dt, limit) == pytest.approx(6 * dt)  # t' + span
    assert trainer.sampler.consistency_time(15 * dt, 14 * dt, limit) == pytest.approx(12 * dt)  # t' - span
    assert trainer.sampler.consistency_time(29 * dt, 30 * dt, limit) == pytest.approx(
        26 * dt
    )  # past the limit
    assert trainer.sampler.consistency_time(2 * dt, dt, limit) == pytest.approx(5 * dt)  # before 0
    off = Trainer(
        _cfg(tiny_scene, tmp_path / "off", settings={"stage2.consistency_frames": 0.0}), progress=False
    )
    assert off.sampler.consistency_time(3 * dt, 4 * dt, limit) == 4 * dt


@pytest.mark.parametrize("stages", [1, 4, 8])
def test_time_range_grows_in_equal_stages(tiny_scene, tmp_path, stages):
    """Over the first ``time_growth_fraction`` of the dynamic stage the sampled range ends at
    t_max * k / stages in stage k (k = 1..stages), and sampled views never lie beyond it."""
    trainer = Trainer(
        _cfg(
            tiny_scene,
            tmp_path / "run",
            dynamic_iterations=1000,
            settings={"stage2.time_growth_fraction": 0.4, "stage2.time_growth_stages": stages},
        ),
        progress=False,
    )
    t_max, per_stage = trainer.t_max, 400 / stages
    for k in range(1, stages + 1):
        for dyn_step in (math.ceil((k - 1) * per_stage), math.ceil(k * per_stage) - 1):
            assert trainer.sampler.time_limit(dyn_step) == pytest.approx(t_max * k / stages)
    assert trainer.sampler.time_limit(400) == trainer.sampler.time_limit(999) == pytest.approx(t_max)
    seen = {trainer.data.views[trainer.sampler.dynamic_view(0)].time for _ in range(200)}
    assert max(seen) <= t_max / stages + 1e-9 and min(seen) == 0.0
    with pytest.raises(ValueError, match="time.growth.stages"):
        Trainer(_cfg(tiny_scene, tmp_path / "bad", settings={"stage2.time_growth_stages": 0}), progress=False)


def test_straight_through_gradient_reaches_deformation_field(tiny_scene, tmp_path):
    trainer = Trainer(_cfg(tiny_scene, tmp_path / "run"), progress=False)
    model = trainer.model
    # give the fields a non-zero output so that gradients are not trivially blocked
    with torch.no_grad():
        for p in model.field_parameters():
            p.add_(0.01 * torch.randn_like(p))
    state = model.training_state(0.25, 0.5)[0]
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
        trainer = Trainer(
            _cfg(tiny_scene, tmp_path / f"run{order}", settings={"dynamics.order": order}), progress=False
        )
        model, g = trainer.model, trainer.model.gaussians
        assert torch.equal(model.deform(0.3)["means"], g["means"])
        for t in (0.0, 0.3, 1.4):
            state = Predictor(model, ExtrapolationState(t_max=0.5)).gaussians_at(t)
            assert torch.allclose(state["means"], g["means"], atol=tol)
            assert torch.allclose(state["scales"], g["scales"])


def test_hexplane_regularisers_join_the_dynamic_loss(tiny_scene, tmp_path):
    cfg = _cfg(tiny_scene, tmp_path / "run", settings={"deformation.kind": "hexplane"})
    trainer = Trainer(cfg, progress=False)
    static = trainer.train_step()  # stage 1: photometric loss only
    assert "plane_tv" not in static
    trainer.state.step = cfg.static_iterations
    stats = trainer.train_step()
    terms = ("plane_tv", "time_smoothness", "time_l1")
    assert all(stats[k] >= 0 for k in terms) and stats["plane_tv"] > 0  # random spatial planes: TV > 0
    photometric = (1 - cfg.optim.ssim_weight) * stats["l1"] + cfg.optim.ssim_weight * (1 - stats["ssim"])
    assert stats["loss"] == pytest.approx(photometric + sum(stats[k] for k in terms), rel=1e-5)


def test_hexplane_box_holds_the_whole_scene_in_the_dynamic_stage(tiny_scene, tmp_path):
    # The dataset's aabb bounds the moving object only; the grid must cover the static scene too,
    # or background beyond the object's box would read (and follow) the features of its edge.
    cfg = _cfg(tiny_scene, tmp_path / "run", settings={"deformation.kind": "hexplane"})
    trainer = Trainer(cfg, progress=False)
    means = trainer.model.gaussians["means"]
    with torch.no_grad():  # a static scene larger than the object's box
        means.mul_(3.0)
    box = trainer.model.deformation.grid.aabb
    before = box.clone()
    trainer.state.step = cfg.static_iterations
    trainer.train_step()
    inside = ((means >= box[0]) & (means <= box[1])).all(dim=1).float().mean()
    assert inside > 0.99
    assert (box[0] <= before[0]).all() and (box[1] >= before[1]).all()


def test_hexplane_planes_train_with_their_own_rate(tiny_scene, tmp_path):
    cfg = _cfg(tiny_scene, tmp_path / "run", settings={"deformation.kind": "hexplane"})
    trainer = Trainer(cfg, progress=False)
    trainer.state.step = cfg.static_iterations
    trainer.train_step()
    groups = {g["name"]: g for g in trainer.state.field_opt.param_groups}
    grid = {id(p) for p in trainer.model.deformation.grid.parameters()}
    assert {id(p) for p in groups["grid"]["params"]} == grid
    assert not grid & {id(p) for p in groups["fields"]["params"]}
    assert groups["grid"]["lr"] == pytest.approx(cfg.optim.grid_lr * trainer.extent)  # 4DGS: x extent
    assert groups["fields"]["lr"] == pytest.approx(cfg.optim.field_lr)


def test_skip_static_moves_only_the_moving_gaussians_and_those_exactly(tiny_scene, tmp_path):
    """With Gaussians marked static, they keep their canonical geometry at every time (training state,
    f_defo, extrapolation) and take no gradient from the fields; the others get the same values as
    when the fields see every Gaussian."""
    model = _perturbed_model(tiny_scene, tmp_path / "a", {"stage2.acceleration_consistency": 0.0})
    g = model.gaussians
    static = torch.rand(g["means"].shape[0], generator=torch.Generator().manual_seed(1)) < 0.5

    def extrapolated():
        return Predictor(model, ExtrapolationState(t_max=0.5)).gaussians_at(1.2)

    whole = [model.deform(0.3), model.training_state(0.25, 0.5)[0], extrapolated()]
    model.set_static_mask(static)
    masked = [model.deform(0.3), model.training_state(0.25, 0.5)[0], extrapolated()]
    moving = ~static
    for full, part in zip(whole, masked, strict=True):
        for name in ("means", "quats"):
            torch.testing.assert_close(part[name][moving], full[name][moving], rtol=1e-5, atol=1e-6)
            assert torch.equal(part[name][static], g[name][static])
            assert not torch.allclose(full[name][static], g[name][static])  # the fields did move them
    assert torch.equal(masked[0]["scales"][static], g["scales"][static])
    weights = torch.randn_like(g["means"])
    loss = (masked[1]["means"][static] * weights[static]).sum()
    grads = torch.autograd.grad(loss, [g["means"], *model.field_parameters()], allow_unused=True)
    torch.testing.assert_close(grads[0][static], weights[static])  # straight to the canonical means
    assert all(x is None or not x.any() for x in grads[1:])


def test_a_scene_marked_static_everywhere_trains_without_the_fields(tiny_scene, tmp_path):
    """Every Gaussian marked static (a still scene): the step renders the canonical Gaussians, and the
    acceleration consistency, a mean over no moving particle, is left out rather than NaN."""
    model = _perturbed_model(tiny_scene, tmp_path / "a", {"stage2.acceleration_consistency": 0.5})
    g = model.gaussians
    model.set_static_mask(torch.ones(g["means"].shape[0], dtype=torch.bool))
    state, losses = model.training_state(0.25, 0.5)
    assert losses == {}
    assert torch.equal(state["means"], g["means"]) and torch.equal(state["quats"], g["quats"])


def test_the_static_margin_keeps_the_still_gaussians_next_to_moving_ones_moving(tiny_scene, tmp_path):
    """A Gaussian that barely moves within the margin of one that moves (a part by its hinge) is not
    frozen; far from every moving one it is."""
    from tracegs.models.trace import near_points

    grid = torch.stack(torch.meshgrid(*[torch.arange(10.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
    seeds = grid[:, 0] >= 5  # the half that moves; the spacing is 1
    near = near_points(grid, seeds, 2.0)
    assert torch.equal(near, grid[:, 0] >= 3)
    assert torch.equal(near_points(grid, seeds, 0.5), seeds)
    model = _perturbed_model(tiny_scene, tmp_path / "a")
    most = model.max_displacement(0.5, 16)
    threshold = float(most.median())
    model.mark_static(threshold, 0.5, margin=3.0)
    still = most < threshold
    assert (model.static_mask <= still).all() and model.static_mask.sum() < still.sum()
    kept = still & ~model.static_mask
    assert torch.equal(kept, still & near_points(model.gaussians["means"].detach(), ~still, 3.0))


def test_skip_static_marks_by_displacement_and_is_kept_in_the_checkpoint(tiny_scene, tmp_path):
    model = _perturbed_model(tiny_scene, tmp_path / "a")
    most = model.max_displacement(0.5, 16)
    threshold = float(most.median())
    assert model.mark_static(threshold, 0.5) == pytest.approx(float((most < threshold).float().mean()))
    assert torch.equal(model.static_mask, most < threshold)
    assert not model.max_displacement(0.5, 16)[model.static_mask].any()
    # in training: marked once, at the step where densification has stopped and every time is sampled
    cfg = _cfg(
        tiny_scene,
        tmp_path / "run",
        dynamic_iterations=4,
        settings={"stage2.skip_static": True, "stage2.static_displacement": 1.0},
    )
    trainer = Trainer(cfg, progress=False)
    marking = trainer._static_marking_step()
    assert marking == max(trainer.strategy.refine_stop, cfg.static_iterations + 1)
    while trainer.state.step <= marking:
        assert (trainer.model.static_mask is None) == (trainer.state.step <= marking)
        trainer.train_step()
    mask = trainer.model.static_mask
    assert mask is not None and trainer.state.static_fraction == pytest.approx(float(mask.float().mean()))
    trainer.save()
    assert torch.equal(Trainer(cfg, progress=False).model.static_mask, mask)  # resumed
    assert Trainer(cfg, progress=False).train()["static_fraction"] == trainer.state.static_fraction
    assert torch.equal(load_run(tmp_path / "run", device="cpu").model.static_mask, mask)


def _move_cameras(scene, scale, offset):
    """Rewrite a scene's camera centres as ``scale * c + offset`` (the same views of a scaled, moved world)."""
    for path in scene.glob("transforms_*.json"):
        meta = json.loads(path.read_text())
        for frame in meta["frames"]:
            for i in range(3):
                frame["transform_matrix"][i][3] = scale * frame["transform_matrix"][i][3] + offset[i]
        path.write_text(json.dumps(meta))


@pytest.mark.parametrize("scale, offset", [(1.0, (0.0, 0.0, 0.0)), (10.0, (50.0, -20.0, 3.0))])
def test_initial_box_follows_the_cameras(tiny_scene, tmp_path, scale, offset):
    # The tiny scene's cameras sit sqrt(3^2 + 1.5^2) from the origin and look at it; the random-init
    # cube must be centred where they look and scale with them, whatever the capture's units.
    _move_cameras(tiny_scene, scale, offset)
    trainer = Trainer(_cfg(tiny_scene, tmp_path / "run"), progress=False)
    half = 1.3 * scale * math.hypot(3.0, 1.5) / 4.031
    expected = torch.tensor(offset) + torch.tensor([[-half] * 3, [half] * 3])
    assert torch.allclose(trainer.aabb, expected, rtol=2e-3, atol=2e-3 * scale)
    means = trainer.model.gaussians["means"]
    assert (means >= trainer.aabb[0]).all() and (means <= trainer.aabb[1]).all()
    fixed = Trainer(_cfg(tiny_scene, tmp_path / "fixed", init_box="origin"), progress=False)
    assert torch.equal(fixed.aabb, torch.tensor([[-1.3] * 3, [1.3] * 3]))


def test_initial_box_of_the_blender_layout_is_the_usual_cube(tiny_scene, tmp_path):
    # Cameras 4.031 from the origin (Blender / D-NeRF): exactly the +/- 1.3 cube of 3DGS's random init.
    _move_cameras(tiny_scene, 4.031 / math.hypot(3.0, 1.5), (0.0, 0.0, 0.0))
    trainer = Trainer(_cfg(tiny_scene, tmp_path / "run"), progress=False)
    assert torch.equal(trainer.aabb, torch.tensor([[-1.3] * 3, [1.3] * 3]))


@pytest.mark.parametrize("fast_bf16", [False, True])
def test_a_bf16_run_is_rendered_in_fp32_on_cpus_without_hardware_bf16(
    tiny_scene, tmp_path, monkeypatch, fast_bf16
):
    import tracegs.run

    cfg = _cfg(tiny_scene, tmp_path / "run", bf16=True)
    Trainer(cfg, progress=False).train()
    machine = dataclasses.replace(tracegs.run.this_machine(), fast_bf16=fast_bf16)
    monkeypatch.setattr(tracegs.run, "this_machine", lambda: machine)
    run = load_run(tmp_path / "run", device="cpu")
    model = run.model
    assert run.config.bf16 and model.bf16 == fast_bf16
    model.set_static_mask(None)  # the fields see every Gaussian, whatever the short run marked static
    with torch.no_grad():  # fields that move the Gaussians (the heads start at zero)
        for param in model.field_parameters():
            param.add_(0.05 * torch.randn_like(param))
    means = model.deform(0.5)["means"]
    model.bf16 = False
    assert torch.equal(means, model.deform(0.5)["means"]) != fast_bf16


@pytest.mark.parametrize("fast_bf16", [False, True])
def test_a_bf16_config_trains_in_fp32_on_cpus_without_hardware_bf16(
    tiny_scene, tmp_path, monkeypatch, fast_bf16
):
    import tracegs.run

    machine = dataclasses.replace(tracegs.run.this_machine(), fast_bf16=fast_bf16)
    monkeypatch.setattr(tracegs.run, "this_machine", lambda: machine)
    trainer = Trainer(
        _cfg(tiny_scene, tmp_path / "run", bf16=True), progress=False
    )  # (as --resume reads one)
    assert trainer.cfg.bf16 and trainer.model.bf16 == fast_bf16
    assert ("fields train in fp32" in trainer.describe()) != fast_bf16
    assert trainer.summary()["fields_dtype"] == ("bf16" if fast_bf16 else "fp32")


def test_describe_names_the_images_steps_and_a_downscale_for_large_images(tiny_scene, tmp_path):
    trainer = Trainer(_cfg(tiny_scene, tmp_path / "run"), progress=False)
    line = trainer.describe()
    assert (
        "trace (tiny) on 9 images of 24x24 px with t <= 0.667" in line
        and "4 steps (1 view(s) a step in stage 2) on cpu" in line
        and "world frame" in line
    )
    assert "note" not in line
    big = Trainer(_cfg(tiny_scene, tmp_path / "big", "cpu-fast"), progress=False)
    big.data.views[0].camera = dataclasses.replace(big.data.views[0].camera, width=800, height=800)
    assert "--downscale 7 trains at about 128 px" in big.describe()
