"""The freeze threshold is chosen on the training images: it must freeze what the images say is static."""

import imageio.v3 as iio
import numpy as np
import torch
from tests.conftest import write_tiny_scene

from tracegs.config import make_config
from tracegs.data.scene import load_scene
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.extrapolate.calibrate import FREEZE_FRACTIONS, choose_freeze_threshold
from tracegs.train.trainer import Trainer


def _setup(tmp_path, drift: float):
    scene = write_tiny_scene(tmp_path / "scene", n_times=9, size=24)
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu")
    cfg.init_points = 400
    trainer = Trainer(cfg, progress=False)
    model = trainer.model
    with torch.no_grad():  # f_defo stays the identity (every Gaussian is static); f_trd drifts along x
        model.dynamics.head.bias[model.dynamics.slices["velocity"]] = torch.tensor([drift, 0.0, 0.0])
        model.gaussians["opacities"].fill_(2.0)
    # the training images become renders of the canonical (unmoving) Gaussians
    data = load_scene(scene, "train")
    background = torch.tensor(data.background)
    state = Predictor(model, ExtrapolationState(t_max=trainer.t_max)).gaussians_at(0.0)
    with torch.no_grad():
        for f in data.frames:
            rgb = model.render(state, f.camera, cfg.sh_degree, background).image.clamp(0, 1)
            rgba = np.concatenate([(rgb.numpy() * 255).round(), np.full((*rgb.shape[:2], 1), 255)], -1)
            iio.imwrite(f.image_path, rgba.astype(np.uint8))
    return trainer, scene


def test_static_scene_with_drifting_dynamics_is_frozen(tmp_path):
    trainer, scene = _setup(tmp_path, drift=2.0)
    state = ExtrapolationState(t_max=trainer.t_max)
    predictor = Predictor(trainer.model, state, trainer.cfg.extrapolation)
    threshold, scores = choose_freeze_threshold(predictor, scene, 1, trainer.t_max, trainer.extent)
    assert len(scores) == len(FREEZE_FRACTIONS)
    assert threshold > 0
    assert scores[threshold] > scores[0.0] + 5.0
    assert state.freeze_threshold is None  # the choice does not leak into the state it was made from


def test_without_drift_nothing_needs_freezing(tmp_path):
    trainer, scene = _setup(tmp_path, drift=0.0)
    state = ExtrapolationState(t_max=trainer.t_max)
    predictor = Predictor(trainer.model, state, trainer.cfg.extrapolation)
    threshold, scores = choose_freeze_threshold(predictor, scene, 1, trainer.t_max, trainer.extent)
    assert threshold == 0.0  # every candidate renders the same images: ties go to the smallest
