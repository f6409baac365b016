"""benchmarks/panoptic.py: the Hold rows are the TRACE run scored with the motion `hold` (no training
of their own), and every row has the moving-region PSNR beside the whole image's."""

from __future__ import annotations

import importlib.util
from pathlib import Path

ROOT = Path(__file__).parents[2]


def _panoptic():
    spec = importlib.util.spec_from_file_location("bench_panoptic", ROOT / "benchmarks" / "panoptic.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _split(psnr: float, moving: float | None) -> dict:
    s = {"frames": 4, "psnr": psnr, "mae_psnr": psnr, "ssim": 0.9}
    return s if moving is None else {**s, "moving": {"mae_psnr": moving}}


def _evaluation(method: str, motion: str) -> dict:
    base = 20.0 if motion == "hold" else 25.0
    cams = {"new_cameras": _split(base, base - 5), "train_cameras": _split(base + 1, None)}
    return {
        "method": method,
        "motion": motion,
        "interpolation": _split(27.0, 22.0),
        "extrapolation": {**_split(base, base - 5), "per_cameras": cams},
        "train_seconds": 100.0,
        "iterations": 10,
        "gaussians": 500,
    }


def test_hold_rows_score_the_trace_run_with_the_motion_hold(tmp_path, monkeypatch):
    panoptic = _panoptic()
    runs = {}
    for name in ("trace", "defgs"):
        runs[name] = tmp_path / name
        runs[name].mkdir()
        (runs[name] / "checkpoint.pt").write_bytes(b"")
    asked = []

    def evaluations(run, motion="trace"):
        asked.append((run.name, motion))
        full = _evaluation(run.name, motion)
        return full, full

    monkeypatch.setattr(panoptic, "_evaluations", evaluations)
    listed = [(runs["defgs"], {"method": "defgs"}), (runs["trace"], {"method": "trace"})]
    rows = panoptic.hold_rows(listed)
    assert asked == [("trace", "hold")] and (runs["trace"] / "panoptic_eval_hold.json").is_file()
    assert {r["method"] for r in rows} == {"Hold"} and len(rows) == 4
    soon = next(r for r in rows if "next" in r["split"])
    assert soon["mae_psnr"] == 20.0 and soon["moving_psnr"] == 15.0
    assert next(r for r in rows if r["split"].startswith("training cameras"))["moving_psnr"] == "-"
    assert rows[0]["train s"] == 100 and set(panoptic.COLUMNS) <= set(rows[0])
    assert panoptic.hold_rows(listed) == rows and len(asked) == 1  # kept while the checkpoint is older
    assert panoptic.hold_rows([(runs["defgs"], {"method": "defgs"})]) == []  # no TRACE run: no Hold
    trace_rows, facts = panoptic.scores(runs["trace"])
    assert {r["method"] for r in trace_rows} == {"TRACE"} and facts["method"] == "trace"
    assert asked[-1] == ("trace", "trace")
