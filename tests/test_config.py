"""Configs: presets resolve, and a saved config reads back equal (JSON, never eval)."""

import pytest

from tracegs.config import PRESETS, TrainConfig, make_config
from tracegs.run import load_config, save_config


@pytest.mark.parametrize("preset", sorted(PRESETS))
def test_config_round_trip(tmp_path, preset):
    cfg = make_config(preset, method="defgs")
    cfg.stage2.dt_frames = 3.0
    cfg.deformation.kind = "hexplane"
    save_config(cfg, tmp_path / "config.json")
    assert load_config(tmp_path / "config.json") == cfg


def test_unknown_preset_and_field(tmp_path):
    with pytest.raises(ValueError, match="available"):
        make_config("nope")
    (tmp_path / "config.json").write_text('{"not_a_field": 1}')
    with pytest.raises(ValueError, match="TrainConfig.not_a_field"):
        load_config(tmp_path / "config.json")


def test_total_iterations():
    cfg = TrainConfig(static_iterations=10, dynamic_iterations=5)
    assert cfg.total_iterations == 15
    cfg.method = "static"
    assert cfg.total_iterations == 10
