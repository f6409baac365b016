"""The model's settings (``models/config.py``): a ``TraceModel`` is handed its sections, not a training
run's whole config, and says what it is through plain attributes."""

import dataclasses

import pytest
import torch

from tracegs.config import TrainConfig, config_to_dict, make_config
from tracegs.models.config import ModelConfig, Stage2Config
from tracegs.models.gaussians import random_gaussians
from tracegs.models.trace import TraceModel

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def _model(settings: ModelConfig) -> TraceModel:
    return TraceModel(settings, random_gaussians(50, AABB, settings.sh_degree), AABB, frame_interval=0.05)


def test_a_run_config_hands_the_model_its_own_sections():
    cfg = make_config("cpu-fast", backend="reference", camera_colour=True)
    settings = cfg.model_config()
    assert settings.stage2 is cfg.stage2 and settings.deformation is cfg.deformation
    assert settings.dynamics is cfg.dynamics
    names = {f.name for f in dataclasses.fields(ModelConfig)}
    assert {name: getattr(settings, name) for name in names} == {name: getattr(cfg, name) for name in names}
    model = _model(settings)
    assert (model.method, model.sh_degree, model.backend, model.bf16) == ("trace", 1, "reference", cfg.bf16)
    assert model.stage2 is cfg.stage2 and model.stage2.integrator == "rk2"
    assert model.dynamics.cfg is cfg.dynamics and model.deformation.cfg is cfg.deformation
    assert model.camera_colour is not None
    assert not hasattr(model, "cfg")


@pytest.mark.parametrize(
    ("method", "use_deformation", "fields"),
    [("trace", True, (True, True)), ("trace", False, (False, True)), ("defgs", True, (True, False))]
    + [("static", True, (False, False))],
)
def test_the_method_chooses_the_fields(method, use_deformation, fields):
    model = _model(ModelConfig(method=method, stage2=Stage2Config(use_deformation=use_deformation)))
    assert (model.deformation is not None, model.dynamics is not None) == fields
    assert model.method == method and model.camera_colour is None


def test_the_saved_config_keeps_stage2_where_it_was():
    saved = config_to_dict(TrainConfig())
    assert saved["stage2"] == dataclasses.asdict(Stage2Config())
    assert {"method", "sh_degree", "backend", "camera_colour", "bf16", "deformation", "dynamics"} <= set(
        saved
    )
