"""Free bodies are chosen on the training images: a part whose images go on along a parabola gets one,
a part whose images stop does not, and the model then moves it as that free body after the handover."""

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from tests.conftest import write_tiny_scene

from tracegs.config import make_config
from tracegs.data.blender import load_scene
from tracegs.physics.free_body import FreeBody, move
from tracegs.train.calibrate import choose_free_bodies
from tracegs.train.trainer import Trainer

V, A = torch.tensor([0.6, 0.0, 0.3]), torch.tensor([0.0, 0.0, -2.0])


def _setup(tmp_path, stop_at: float | None):
    """A tiny scene whose training images are renders of the model's canonical Gaussians, those with
    x > 0 carried along the parabola ``V t + A t^2 / 2`` (until ``stop_at``, where the images' part
    stops; f_defo follows the parabola throughout). f_trd is zero: its physics holds the part still."""
    scene = write_tiny_scene(tmp_path / "scene", n_times=17, size=32)
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu")
    cfg.init_points = 400
    dyn = cfg.dynamic
    dyn.free_bodies, dyn.handover_frames, dyn.free_body_window, dyn.free_body_backtest = True, 2, 4, 4
    dyn.hold_unseen, dyn.stay_on_surface = 0.0, 0.0
    trainer = Trainer(cfg, progress=False)
    model = trainer.model
    model.freeze_threshold = 0.0
    g = model.gaussians
    with torch.no_grad():
        g["opacities"].fill_(2.0)
        g["scales"].fill_(-3.0)
    part = g["means"][:, 0] > 0

    def path(t: float) -> torch.Tensor:
        return V * t + 0.5 * A * t * t

    def deform(t: float, stop: float | None = None) -> dict[str, torch.Tensor]:
        shift = path(t if stop is None else min(t, stop))
        means = torch.where(part[:, None], g["means"] + shift, g["means"])
        return {"means": means.detach(), "quats": g["quats"].detach(), "scales": g["scales"].detach()}

    data = load_scene(scene, "train")
    background = torch.tensor(data.background)
    with torch.no_grad():
        for f in data.frames:
            state = deform(f.time, stop_at)
            rgb = model.render(state, f.camera, cfg.sh_degree, background).image.clamp(0, 1)
            rgba = np.concatenate([(rgb.numpy() * 255).round(), np.full((*rgb.shape[:2], 1), 255)], -1)
            iio.imwrite(f.image_path, rgba.astype(np.uint8))
    model.deform = deform  # f_defo as the parabola, exactly
    return trainer, model, part, scene


@pytest.mark.parametrize("stop_at", [None, 0.375])
def test_free_body_is_chosen_where_the_images_follow_it(tmp_path, stop_at):
    trainer, model, part, scene = _setup(tmp_path, stop_at)
    chosen, report = choose_free_bodies(model, scene, 1, trainer.t_max, trainer.extent)
    assert len(report) == 1 and report[0]["gaussians"] == int(part.sum())  # the moving part, found whole
    if stop_at is not None:  # the images stop where the backtest starts, as f_trd's physics does
        assert report[0]["mse_learned"] < report[0]["mse_free_body"]
        assert len(chosen["bodies"]) == 0 and not chosen["labels"].any()
        return
    assert report[0]["mse_free_body"] < 0.5 * report[0]["mse_learned"]
    assert torch.equal(chosen["labels"] > 0, part)
    t0 = model.handover_time(trainer.t_max)
    body = FreeBody.from_tensor(chosen["bodies"][0])
    torch.testing.assert_close(body.a, A.double(), rtol=0, atol=1e-4)
    torch.testing.assert_close(body.v, (V + A * t0).double(), rtol=0, atol=1e-4)
    torch.testing.assert_close(body.w, torch.zeros(3, dtype=torch.float64), rtol=0, atol=1e-6)

    # the model moves the part as that body after the handover, the rest by the learned physics
    model.free_bodies = chosen
    t = trainer.t_max + 0.3
    state = model.state_at(t, trainer.t_max)
    start = model.deform(t0)
    want, _ = move(start["means"][part], start["quats"][part], body, t - t0)
    torch.testing.assert_close(state["means"][part], want)
    torch.testing.assert_close(state["means"][part], model.deform(t)["means"][part], rtol=0, atol=1e-4)
    learned = model._physics_from(t0, t)
    torch.testing.assert_close(state["means"][~part], learned["means"][~part])
    model.cfg.dynamic.free_bodies = False  # switched off: the learned physics everywhere
    torch.testing.assert_close(model.state_at(t, trainer.t_max)["means"], learned["means"])
