"""Long horizons: renders past the data, scored only where there are images, and said so."""

from __future__ import annotations

import pytest

from tracegs.config import make_config
from tracegs.eval.horizon import long_horizon
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
    assert result["cameras"] == [3]  # the one camera training never used
    assert len(list((tmp_path / "horizon").glob("*.png"))) == len(rows)
    assert "nothing checks them" in result["note"]
