"""Continual learning: the rounds' windows, a round never trains on a frame past its window, and a
warm round starts from the previous round's parameters."""

from __future__ import annotations

import json

import pytest
import torch
from tests.conftest import write_tiny_scene

from tracegs.config import make_config
from tracegs.continual import Continual, round_config, round_ends, train_continual
from tracegs.run import CHECKPOINT, load_tensors


def test_round_ends_of_the_two_protocols():
    times = [i / 20 for i in range(21)]
    ends = round_ends(times, Continual(window=0.15, horizon=0.15))
    assert [(round(a, 6), round(b, 6)) for a, b in ends] == [
        (0.15, 0.3), (0.3, 0.45), (0.45, 0.6), (0.6, 0.75), (0.75, 0.9), (0.9, 1.0)
    ]  # fmt: skip
    frames = [i / 149 for i in range(150)]  # 150 frames: 15, then one more per round, predict 10
    ends = round_ends(frames, Continual(window=15, horizon=10, step=1, frames=True))
    assert ends[0] == pytest.approx((15 / 149, 25 / 149)) and ends[1][0] == pytest.approx(16 / 149)
    assert ends[-1][0] == pytest.approx(148 / 149) and ends[-1][1] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="nothing"):
        round_ends(times, Continual(window=1.0))


def test_a_warm_round_trains_a_fraction_without_static_stage():
    cfg = make_config("cpu-fast")
    rc = round_config(cfg, 2, 0.45, Continual(fraction=0.25))
    assert rc.t_train_end == 0.45 and rc.run.name == "round_02" and rc.static_iterations == 0
    assert rc.dynamic_iterations == cfg.dynamic_iterations // 4 and rc.densify.refine_stop == 0
    assert round_config(cfg, 0, 0.15, Continual()).static_iterations == cfg.static_iterations


def test_rounds_never_see_frames_past_their_window_and_start_warm(tmp_path, monkeypatch):
    data = write_tiny_scene(tmp_path / "scene", n_cams=4, n_times=7, t_train_end=1.0)
    (data / "transforms_test.json").unlink()  # (empty: every time is in the train split)
    cfg = make_config("tiny", data=data, run=tmp_path / "run", init_points=60)
    seen, starts = [], []
    from tracegs.train import trainer as trainer_module

    original = trainer_module.Trainer.__init__

    def recording_init(self, cfg, progress=True, warm_start=None):
        original(self, cfg, progress=progress, warm_start=warm_start)
        seen.append((float(self.data.times.max()), cfg.t_train_end))
        starts.append((warm_start, {k: v.detach().clone() for k, v in self.model.state_dict().items()}))

    monkeypatch.setattr(trainer_module.Trainer, "__init__", recording_init)
    table = train_continual(cfg, Continual(window=0.3, horizon=0.3), with_lpips=False, progress=False)
    assert [r["observed_until"] for r in table["rounds"]] == [0.3, 0.6, 0.9]
    assert all(r["frames"] > 0 and r["psnr"] > 0 for r in table["rounds"])
    assert all(t_seen <= t_end + 1e-9 for t_seen, t_end in seen) and len(seen) == 3
    assert json.loads((tmp_path / "run" / "continual.json").read_text())["rounds"] == table["rounds"]
    for warm, state in starts[1:]:  # each warm round starts where the one before it ended
        before = load_tensors(warm / CHECKPOINT)["model"]
        assert set(before) == set(state)
        assert all(torch.equal(before[k].cpu(), state[k].cpu()) for k in state)


def test_arriving_frames_are_the_training_cameras_later_frames(tiny_scene):
    from tracegs.data.dataset import ViewDataset

    plain = ViewDataset(tiny_scene, "train")
    arriving = ViewDataset(tiny_scene, "train", arriving=True)
    assert float(plain.times.max()) < 1.0 and float(arriving.times.max()) == 1.0
    added = arriving.views[len(plain) :]
    assert len(added) == 3 and {v.camera_id for v in added} == {v.camera_id for v in plain.views}
    assert len(ViewDataset(tiny_scene, "train", t_max=0.9, arriving=True)) == len(plain)
