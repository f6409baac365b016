"""Long horizons: renders past the data, scored only where there are images, and said so."""

from __future__ import annotations

import pytest
import torch

from tracegs.config import make_config
from tracegs.eval.horizon import long_horizon
from tracegs.extrapolate import Predictor
from tracegs.run import load_run
from tracegs.train.trainer import Trainer


def test_the_long_horizon_says_where_nothing_was_checked(tiny_scene, tmp_path):
    Trainer(
        make_config("tiny", data=tiny_scene, run=tmp_path / "run", init_points=60), progress=False
    ).train()
    result = long_horizon(tmp_path / "run", 2.0, out=tmp_path / "horizon")
    rows = result["per_time"]
    # the tiny scene's 4 times are 1/3 apart, trained up to 2/3: 1, 4/3, 5/3, 2
    assert [r["t"] for r in rows] == pytest.approx([1.0, 4 / 3, 5 / 3, 2.0], abs=1e-5)
    assert result["checked_until"] == pytest.approx(1.0) and result["rendered_until"] == pytest.approx(2.0)
    assert "psnr" in rows[0] and all("psnr" not in r for r in rows[1:])  # no image after t = 1
    assert all(0 <= r["in_sight"] <= 1 for r in rows)
    assert all(r["spread"] > 0 for r in rows)  # (how far apart what moves lies, against t_max)
    assert result["cameras"] == [3]  # the one camera training never used
    assert len(list((tmp_path / "horizon").glob("*.png"))) == len(rows)
    assert "nothing checks them" in result["note"]


def test_a_run_whose_scene_moved_names_the_folder_and_asks_for_data(tiny_scene, tmp_path):
    import shutil

    from tracegs.run import run_data

    scene = tmp_path / "mine"
    shutil.copytree(tiny_scene, scene)
    Trainer(make_config("tiny", data=scene, run=tmp_path / "run", init_points=60), progress=False).train()
    scene.rename(tmp_path / "moved")
    with pytest.raises(
        FileNotFoundError, match=r"mine: no scene here.*trained with --data .*mine.*--data DIR"
    ):
        long_horizon(tmp_path / "run", 1.5)
    assert run_data(make_config("tiny", data=scene), tmp_path / "moved") == tmp_path / "moved"


def test_in_sight_is_the_share_of_what_moves_that_stays_near(tiny_scene, tmp_path, monkeypatch):
    from tracegs.models.trace import TraceModel

    Trainer(
        make_config("tiny", data=tiny_scene, run=tmp_path / "run", init_points=60), progress=False
    ).train()
    real = Predictor.gaussians_at

    def flying(self, t, motion="trace"):  # the first quarter of the Gaussians leave after the training span
        g = dict(real(self, t, motion))
        if t > self.t_max + 1e-6:
            g["means"] = g["means"].clone()
            g["means"][: len(g["means"]) // 4] += 100.0
        return g

    monkeypatch.setattr(Predictor, "gaussians_at", flying)
    rows = long_horizon(tmp_path / "run", 1.5, out=tmp_path / "h1")["per_time"]
    model = load_run(tmp_path / "run", "cpu").model
    n = len(model.gaussians["means"])
    moving = torch.arange(n) if model.moving_rows is None else model.moving_rows.cpu()
    staying = 1 - float((moving < n // 4).float().mean())  # of those the fields move, the ones not sent off
    share = rows[0]["in_sight"]
    assert share == pytest.approx(staying, abs=0.02) and all(r["in_sight"] == share for r in rows)
    assert 0.5 < staying < 1
    # with the fields moving only the leaving quarter (the rest held static), nothing moving stays
    quarter = property(lambda self: torch.arange(len(self.gaussians["means"]) // 4))
    monkeypatch.setattr(TraceModel, "moving_rows", quarter)
    assert long_horizon(tmp_path / "run", 1.5, out=tmp_path / "h2")["per_time"][0]["in_sight"] == 0.0


def test_spread_is_the_neighbours_distance_and_grows_when_what_moves_scatters():
    from tracegs.eval.horizon import _sample, spread

    grid = torch.stack(torch.meshgrid(*(torch.arange(6.0),) * 3, indexing="ij"), -1).reshape(-1, 3)
    sample = _sample(len(grid))
    assert spread(grid, sample) == pytest.approx(1.0)  # a unit grid: the 4 nearest at distance 1
    assert spread(3.0 * grid, sample) == pytest.approx(3.0)  # scattered three times as far apart
    assert spread(grid + 5.0, sample) == pytest.approx(1.0)  # moved as a whole: the same spread
    assert spread(grid[:1], _sample(1)) == 0.0
