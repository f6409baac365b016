"""The demo's pipeline end to end, on a tiny scene and the tiny preset (the scene is placed where the
demo would synthesise it, so the test does not render one)."""

from __future__ import annotations

import json

from tests.conftest import write_tiny_scene
from tracegs.demo import run_demo


def test_demo_trains_evaluates_and_writes_a_video(tmp_path, capsys):
    write_tiny_scene(tmp_path / "scene", size=32)  # LPIPS-alex needs >= 31 px
    result = run_demo(tmp_path, preset="tiny", device="cpu")
    metrics = json.loads((tmp_path / "trace" / "eval.json").read_text())
    assert result["extrapolation_psnr"] == metrics["extrapolation"]["mae_psnr"]
    assert metrics["extrapolation"]["frames"] > 0 and metrics["interpolation"]["frames"] > 0
    assert (tmp_path / "trace" / "renders" / "sweep.mp4").stat().st_size > 0
    assert any((tmp_path / "trace" / "eval" / "extrapolation").glob("*.png"))
    printed = capsys.readouterr().out
    assert f"{metrics['extrapolation']['mae_psnr']:.2f}" in printed and "sweep.mp4" in printed
