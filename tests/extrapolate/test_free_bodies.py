"""Free bodies are chosen after training: a part in flight whose images go on along a parabola gets
one; a part whose images stop, or one that touches something still, does not; and the model then
moves a chosen part as its free body after the handover."""

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from tests.conftest import write_tiny_scene

from tracegs.config import make_config
from tracegs.data.scene import load_scene
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.extrapolate.free_bodies import choose_free_bodies, legendre_to_path
from tracegs.extrapolate.state import STATE_VERSION
from tracegs.physics.free_body import FreeBody, move
from tracegs.run_compat import state_from_old_checkpoint
from tracegs.train.trainer import Trainer

V, A = torch.tensor([0.6, 0.0, 0.3]), torch.tensor([0.0, 0.0, -2.0])


def _setup(tmp_path, stop_at: float | None, gap: float, bend: torch.Tensor | None = None):
    """A tiny scene of two blobs of Gaussians ``gap`` apart, whose training images are renders of the
    model: the still blob at its place, the other carried along the parabola ``V t + A t^2 / 2``
    (until ``stop_at``, where the images' blob stops; f_defo follows the parabola throughout, bent by
    ``bend (t - t0)^2 / 2`` away from it about the handover t0 when given). f_trd is zero: its physics
    holds the blob still. Returns the trainer, the model, its predictor with the state so far (no freeze
    threshold, no unseen Gaussians), the moving blob's rows and the scene."""
    scene = write_tiny_scene(tmp_path / "scene", n_times=17, size=32)
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu")
    cfg.init_points = 400
    dyn = cfg.extrapolation
    dyn.free_bodies, dyn.handover_frames, dyn.free_body_window, dyn.free_body_backtest = True, 2, 4, 4
    dyn.hold_unseen, dyn.hold_surface = False, False
    dyn.free_body_refine_steps = 0  # the fit to f_defo's path, exactly (the fit to the images: below)
    trainer = Trainer(cfg, progress=False)
    model = trainer.model
    state = ExtrapolationState(t_max=trainer.t_max, freeze_threshold=0.0)
    predictor = Predictor(model, state, cfg.extrapolation)
    g = model.gaussians
    n = g["means"].shape[0]
    part = torch.arange(n) < n // 2
    blob = torch.randn(n, 3, generator=torch.Generator().manual_seed(0)) * 0.05
    with torch.no_grad():
        g["means"].copy_(blob + torch.where(part[:, None], 0.5 * gap, -0.5 * gap) * torch.tensor([1.0, 0, 0]))
        g["opacities"].fill_(2.0)
        g["scales"].fill_(-3.5)

    t0 = predictor.handover_time()

    def deform(t: float, stop: float | None = None, bent: bool = True) -> dict[str, torch.Tensor]:
        s = t if stop is None else min(t, stop)
        path = V * s + 0.5 * A * s * s
        if bend is not None and bent:
            path = path + 0.5 * bend * (t - t0) ** 2
        means = torch.where(part[:, None], g["means"] + path, g["means"])
        return {"means": means.detach(), "quats": g["quats"].detach(), "scales": g["scales"].detach()}

    data = load_scene(scene, "train")
    background = torch.tensor(data.background)
    with torch.no_grad():
        for f in data.frames:
            rgb = model.render(
                deform(f.time, stop_at, bent=False), f.camera, cfg.sh_degree, background
            ).image.clamp(0, 1)
            rgba = np.concatenate([(rgb.numpy() * 255).round(), np.full((*rgb.shape[:2], 1), 255)], -1)
            iio.imwrite(f.image_path, rgba.astype(np.uint8))
    model.deform = deform  # f_defo as the parabola, exactly
    return trainer, model, predictor, part, scene


@pytest.mark.parametrize("stop_at, gap", [(None, 0.8), (0.375, 0.8), (None, 0.1)])
def test_free_body_is_chosen_for_a_part_in_flight_that_the_images_follow(tmp_path, stop_at, gap):
    trainer, model, predictor, part, scene = _setup(tmp_path, stop_at, gap)
    chosen, report = choose_free_bodies(predictor, scene, 1, trainer.extent)
    assert len(report) == 1 and report[0]["gaussians"] == int(part.sum())  # the moving blob, found whole
    if gap < 0.2:  # touching the still blob: never a free body, and no backtest
        assert report[0]["isolation"] < predictor.settings.free_body_isolation
        assert "mse_free_body" not in report[0] and not chosen["labels"].any()
        return
    assert report[0]["isolation"] > predictor.settings.free_body_isolation
    if stop_at is not None:  # the images stop where the backtest starts, as f_trd's physics does
        assert report[0]["mse_free_body"] > predictor.settings.free_body_tolerance * report[0]["mse_learned"]
        assert len(chosen["bodies"]) == 0 and not chosen["labels"].any()
        return
    assert report[0]["mse_free_body"] < 0.5 * report[0]["mse_learned"]
    assert torch.equal(chosen["labels"] > 0, part)
    t0 = predictor.handover_time()
    body = FreeBody.from_tensor(chosen["bodies"][0])
    torch.testing.assert_close(body.a, A.double(), rtol=0, atol=1e-4)
    torch.testing.assert_close(body.v, (V + A * t0).double(), rtol=0, atol=1e-4)
    torch.testing.assert_close(body.w, torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-6)

    # the model moves the part as that body after the handover, the rest by the learned physics
    predictor.state.free_bodies = chosen
    t = trainer.t_max + 0.3
    gaussians = predictor.gaussians_at(t)
    start = model.deform(t0)
    want, _ = move(start["means"][part], start["quats"][part], body, t - t0)
    torch.testing.assert_close(gaussians["means"][part], want)
    torch.testing.assert_close(gaussians["means"][part], model.deform(t)["means"][part], rtol=0, atol=1e-4)
    learned = predictor.physics_from(t0, t)
    torch.testing.assert_close(gaussians["means"][~part], learned["means"][~part])
    predictor.settings.free_bodies = False  # switched off: the learned physics everywhere
    torch.testing.assert_close(predictor.gaussians_at(t)["means"], learned["means"])


def test_free_body_is_fitted_to_the_images_where_f_defo_is_off(tmp_path):
    """f_defo's parabola bends away from the images' before and after the handover (an acceleration
    off by 1.8); the fit to f_defo's centroid takes its path, the refinement on the images comes back
    to the truth."""
    trainer, model, predictor, part, scene = _setup(tmp_path, None, 0.8, bend=torch.tensor([1.5, 0.0, 1.0]))
    t0 = predictor.handover_time()
    centre = model.gaussians["means"][part].detach().double().mean(0)
    errors, acceleration_errors = {}, {}
    for steps in (0, 60, 150):
        predictor.settings.free_body_refine_steps = steps
        chosen, _ = choose_free_bodies(predictor, scene, 1, trainer.extent)
        assert torch.equal(chosen["labels"] > 0, part)
        body = FreeBody.from_tensor(chosen["bodies"][0])
        acceleration_errors[steps] = float((body.a - A.double()).norm() / A.norm())
        start = (centre + V.double() * t0 + 0.5 * A.double() * t0 * t0)[None].float()  # f_defo's at t0
        errors[steps] = []
        for t in (trainer.t_max, trainer.t_max + 0.25):  # the end of the data, and a little later
            moved, _ = move(start, torch.tensor([[1.0, 0.0, 0.0, 0.0]]), body, t - t0)
            truth = centre + V.double() * t + 0.5 * A.double() * t * t
            errors[steps].append(float((moved[0].double() - truth).norm()))
    assert min(errors[0]) > 0.01  # the fit to f_defo inherits its error
    assert max(errors[150]) < 0.25 * min(errors[0])
    # the acceleration settles early: steps in the Legendre coefficients, not in v and a (correlated
    # over the window: 60 steps in those left it 0.23 of |A| off)
    assert acceleration_errors[0] > 0.5 and acceleration_errors[60] < 0.05
    assert acceleration_errors[150] < 0.01


def test_legendre_steps_add_their_polynomials_to_the_path():
    """``legendre_to_path``: the (v, a, shift) change it gives moves the pivot by c0 P0 + c1 P1 + c2 P2
    over the span, with ``t0`` inside the span, at its end, or past it."""
    generator = torch.Generator().manual_seed(0)
    lo, hi = 0.3, 0.55
    for t0 in (0.4, 0.55, 0.7):
        c = torch.randn(3, generator=generator, dtype=torch.float64)
        dv, da, shift = legendre_to_path(lo, hi, t0) @ c
        for t in torch.linspace(lo, hi, 7, dtype=torch.float64):
            x, s = (2 * t - lo - hi) / (hi - lo), t - t0
            want = c[0] + c[1] * x + c[2] * (3 * x**2 - 1) / 2
            torch.testing.assert_close(shift + dv * s + da * s * s / 2, want, rtol=0, atol=1e-12)


def test_free_bodies_fitted_by_an_earlier_version_are_chosen_again():
    """Bodies of 12 numbers (no shift; fitted before the centre of mass and the images) read as not
    chosen, in a saved post-training state and in a checkpoint of an earlier version alike, so that
    loading the run asks for ``tracegs calibrate``, which chooses them again with this version's fit."""
    labels = torch.zeros(5, dtype=torch.long)

    def saved(bodies):
        return {
            "version": STATE_VERSION,
            "t_max": 0.75,
            "freeze_threshold": 0.0,
            "unseen": None,
            "free_bodies": bodies,
        }

    assert ExtrapolationState.from_dict(saved(None)).free_bodies is None
    for old in (torch.zeros(1, 12), torch.zeros(0, 12)):
        with pytest.raises(ValueError, match="12 numbers"):
            ExtrapolationState.from_dict(saved({"t0": 0.5, "labels": labels, "bodies": old}))
    current = {"t0": 0.5, "labels": labels, "bodies": torch.zeros(1, 15, dtype=torch.float64)}
    state = ExtrapolationState.from_dict(saved(current))
    assert state.free_bodies["t0"] == 0.5 and torch.equal(state.free_bodies["bodies"], current["bodies"])
    assert torch.equal(state.free_bodies["labels"], labels)

    def checkpoint(bodies):
        config = {"dynamic": {"free_bodies": True, "hold_unseen": 0.0}}  # no unseen mask to hold
        return {
            "config": config,
            "t_max": 0.75,
            "freeze_threshold": 0.0,
            "unseen_mask": None,
            "free_bodies": bodies,
        }

    for old in (None, torch.zeros(1, 12), torch.zeros(0, 12)):
        bodies = None if old is None else {"t0": 0.5, "labels": labels, "bodies": old}
        assert state_from_old_checkpoint(checkpoint(bodies), "cpu") is None
    state = state_from_old_checkpoint(checkpoint(current), "cpu")
    assert state is not None and torch.equal(state.free_bodies["bodies"], current["bodies"])
