"""The trained run as one object: what ``Predictor`` composes (deform, physics, render) against the
model's own pieces, its settings and its checks."""

import math

import pytest
import torch
from tests.conftest import randomised_model

from tracegs.config import make_config
from tracegs.data.cameras import Camera, look_at_viewmat
from tracegs.extrapolate import MAX_TIME_FACTOR, ExtrapolationState, Predictor, check_time
from tracegs.extrapolate.predictor import MOTIONS

T_MAX = 0.5


def _predictor(**settings) -> Predictor:
    cfg = make_config("tiny", device="cpu", bf16=False)
    for name, value in settings.items():
        setattr(cfg.extrapolation, name, value)
    model = randomised_model(cfg)
    return Predictor(model, ExtrapolationState(t_max=T_MAX), cfg.extrapolation, torch.ones(3))


def _camera() -> Camera:
    K = torch.tensor([[40.0, 0, 16], [0, 40, 16], [0, 0, 1]])
    return Camera(look_at_viewmat((2.5, 1.0, 1.5)), K, 32, 32)


def test_up_to_the_handover_it_is_f_defo_and_after_it_the_integrated_physics():
    predictor = _predictor(hold_unseen=False, hold_surface=False, freeze_static=False)
    model, t0 = predictor.model, predictor.handover_time()
    assert t0 == pytest.approx(T_MAX - predictor.settings.handover_frames * model.dt_max)
    with torch.no_grad():
        for t in (0.0, 0.5 * t0, t0):
            assert torch.equal(predictor.gaussians_at(t)["means"], model.deform(t)["means"])
        late = predictor.gaussians_at(T_MAX + 0.3)
        assert torch.equal(late["means"], predictor.physics_from(t0, T_MAX + 0.3)["means"])
        assert (late["means"] - model.deform(T_MAX + 0.3)["means"]).abs().max() > 1e-4  # not f_defo
        assert torch.equal(
            predictor.gaussians_at(T_MAX + 0.3, "f_defo")["means"], model.deform(T_MAX + 0.3)["means"]
        )
    with pytest.raises(ValueError, match="motion 'physics'"):
        predictor.gaussians_at(1.0, "physics")


def test_hold_is_f_defo_up_to_the_span_end_and_its_state_there_afterwards():
    predictor = _predictor()
    model = predictor.model
    with torch.no_grad():
        for t in (0.0, 0.3 * T_MAX, predictor.handover_time(), T_MAX):  # before t_max: f_defo
            held, deformed = predictor.gaussians_at(t, "hold"), model.deform(t)
            assert all(torch.equal(held[k], deformed[k]) for k in ("means", "quats", "scales"))
        last = model.deform(T_MAX)
        for t in (T_MAX + 1e-3, T_MAX + 0.3, 4 * T_MAX):  # after it: f_defo's Gaussians at t_max, still
            held = predictor.gaussians_at(t, "hold")
            assert all(torch.equal(held[k], last[k]) for k in ("means", "quats", "scales"))
        assert (model.deform(T_MAX + 0.3)["means"] - last["means"]).abs().max() > 1e-4  # f_defo moves on
    assert "hold" in MOTIONS


def test_a_render_is_the_models_render_of_the_gaussians_at_that_time_in_its_colours():
    predictor = _predictor()
    model, camera, t = predictor.model, _camera(), T_MAX + 0.2
    with torch.no_grad():
        want = model.render(predictor.gaussians_at(t), camera, model.sh_degree, torch.ones(3)).image
    got = predictor.render(camera, t)
    assert got.shape == (32, 32, 3) and got.std() > 0.01
    assert torch.equal(got, want.clamp(0, 1))
    on_black = predictor.with_background(None).render(camera, t)
    assert on_black.sum() < got.sum()  # no background given: black
    params = predictor.parameters_at(t)
    assert torch.equal(params["means"], predictor.gaussians_at(t)["means"])
    assert torch.equal(params["sh0"], model.gaussians["sh0"])


def test_labels_render_each_gaussian_in_its_segment():
    predictor = _predictor()
    n = predictor.model.gaussians["means"].shape[0]
    one, _ = predictor.render_labels(_camera(), torch.zeros(n, dtype=torch.long), 1, t=0.2)
    assert set(one.ravel().tolist()) <= {0, 1} and (one == 1).any()
    two, confidence = predictor.render_labels(_camera(), torch.arange(n) % 2, 2, t=0.2)
    assert {1, 2} <= set(two.ravel().tolist()) and ((confidence >= 0) & (confidence <= 1)).all()
    assert ((two > 0) == (one > 0)).all()  # the same pixels are covered, whatever the labels


def test_settings_changed_for_rendering_leave_the_original_as_it_was():
    predictor = _predictor(joint_laws=True)
    off = predictor.with_settings(joint_laws=False)
    assert predictor.settings.joint_laws and not off.settings.joint_laws
    assert off.state is predictor.state and off.model is predictor.model
    with pytest.raises(TypeError):
        predictor.with_settings(no_such_setting=1)


def test_times_are_checked_against_the_runs_span():
    predictor = _predictor()
    assert predictor.check_time(MAX_TIME_FACTOR * T_MAX) == MAX_TIME_FACTOR * T_MAX
    with pytest.raises(ValueError, match="--t-end 5.5 is beyond the limit 5"):
        predictor.check_time(5.5, "--t-end")
    for bad in (-0.1, math.nan, math.inf):
        with pytest.raises(ValueError, match="finite time >= 0"):
            check_time(bad, T_MAX)


def test_the_description_says_what_it_predicts_with():
    predictor = _predictor()
    predictor.state.freeze_threshold = 0.01
    about = predictor.describe()
    assert about["method"] == "trace" and about["t_max"] == T_MAX
    assert about["gaussians"] == predictor.model.gaussians["means"].shape[0]
    assert about["handover"] == pytest.approx(predictor.handover_time())
    assert about["freeze_threshold"] == 0.01 and about["free_bodies"] == 0 and about["joint_parts"] == 0
