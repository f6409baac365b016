"""A variant table's rows run as Ray tasks (``cluster``) are the rows of the run in order, a row that
differs only after training waits for its scene's TRACE cell, and a missing ray is one clear line."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import write_tiny_scene
from tracegs.bench import METHODS, run_variant_table
from tracegs.bench.sweep import RAY_MISSING, Cell, RayMissing, dependencies, run_cells, schedule
from tracegs.results import read_record

TIMINGS = ("train_s", "ms_per_it")


def _scores(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k not in TIMINGS and not k.startswith("ms_")} for r in rows]


def test_the_rows_on_a_local_ray_are_the_rows_in_order(tmp_path, capsys):
    ray = pytest.importorskip("ray")
    scenes = (str(write_tiny_scene(tmp_path / "scene", size=32)),)  # LPIPS needs >= 31 px
    variants = {k: METHODS[k] for k in ("TRACE", "DefGS", "TRACE joint laws")}
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # as each Ray task: the same thread count trains the same bits
    try:
        rows = run_variant_table(
            "methods", variants, tmp_path / "here", scenes, "tiny", json_path=tmp_path / "here.json"
        )
    finally:
        torch.set_num_threads(threads)
    try:
        on_ray = run_variant_table(
            "methods",
            variants,
            tmp_path / "ray",
            scenes,
            "tiny",
            json_path=tmp_path / "ray.json",
            cluster="auto",
        )
        assert not ray.is_initialized()  # the Ray it started is shut down
    finally:
        ray.shutdown()
    assert [(r["scene"], r["variant"]) for r in on_ray] == [("scene", v) for v in variants]
    assert _scores(on_ray) == _scores(rows)
    assert _scores(read_record(tmp_path / "ray.json")["rows"]) == _scores(
        read_record(tmp_path / "here.json")["rows"]
    )
    # the joint-laws row ran after its TRACE cell: it copied that training instead of training again
    assert on_ray[2]["train_s"] == on_ray[0]["train_s"]
    assert "the training of" in capsys.readouterr().out  # the task's printed line reaches the driver
    runs = sorted(p.name for p in (tmp_path / "ray" / "runs").iterdir())
    assert runs == sorted(p.name for p in (tmp_path / "here" / "runs").iterdir())


def _cell(scene: str, slug: str, after_training_only: bool = False) -> Cell:
    run = Path("runs") / f"{scene}_{slug}_tiny"
    return Cell(scene, slug, run, None, run.with_name(f"{scene}_TRACE_tiny"), after_training_only)


def test_a_row_that_differs_after_training_runs_after_its_trace_cell():
    cells = [
        _cell("a", "joint", after_training_only=True),  # listed before its TRACE cell
        _cell("a", "TRACE"),
        _cell("a", "DefGS"),
        _cell("b", "joint", after_training_only=True),  # no TRACE cell of b here: trains on its own
        _cell("a", "TRACE"),  # a second row of the TRACE folder (the ablation "dt=2")
    ]
    assert dependencies(cells) == {0: 1, 4: 1}
    assert schedule(cells) == [1, 0, 2, 3, 4]  # only a cell listed before the one it waits for moves
    table = [_cell("a", "TRACE"), _cell("a", "DefGS"), _cell("a", "joint", after_training_only=True)]
    assert schedule(table) == [0, 1, 2]  # TRACE listed first: the table's order


def test_a_missing_ray_is_one_clear_line(tmp_path, monkeypatch, capsys):
    from tracegs.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    with pytest.raises(RayMissing, match="ray is not installed"):
        run_cells([_cell("a", "TRACE")], cluster="auto")
    scene = str(write_tiny_scene(tmp_path / "scene", size=32))
    with pytest.raises(SystemExit) as exit_:
        main(["bench", "methods", "--scenes", scene, "--out", str(tmp_path / "bench"), "--cluster", "auto"])
    assert exit_.value.code == 1
    err = capsys.readouterr().err
    assert RAY_MISSING in err and "Traceback" not in err
    assert not (tmp_path / "bench" / "runs").exists()  # nothing trained


def test_the_hold_row_is_the_trace_run_scored_with_another_motion(tmp_path, monkeypatch):
    import tracegs.bench.variants as variants

    assert "Hold" in METHODS and variants.MOTIONS == {"Hold": "hold"}
    cells = []
    monkeypatch.setattr(variants, "run_cells", lambda c, *a: cells.extend(c) or [])
    scene = str(write_tiny_scene(tmp_path / "scene", size=32))
    table = {k: METHODS[k] for k in ("Hold", "TRACE", "DefGS")}  # Hold listed first on purpose
    run_variant_table("methods", table, tmp_path / "bench", (scene,), "tiny")
    hold, trace, defgs = cells
    assert (hold.label, hold.motion, trace.motion, defgs.motion) == ("Hold", "hold", "trace", "trace")
    assert hold.run == trace.run and hold.cfg == trace.cfg  # TRACE's run folder and settings
    assert dependencies(cells) == {0: 1}  # it waits for the TRACE cell, which trains that folder
    assert schedule(cells) == [1, 0, 2]


def _finished_run(run: Path, psnr: float) -> None:
    import json

    run.mkdir(parents=True)
    split = {"mae_psnr": psnr, "ssim": 0.9, "frames": 2}
    (run / "eval.json").write_text(json.dumps({"interpolation": split, "extrapolation": split}))
    facts = {"train_seconds": 5.0, "iterations": 10, "gaussians": 100, "ms_per_iteration": {}}
    (run / "summary.json").write_text(json.dumps(facts))


def test_the_hold_row_scores_a_finished_trace_run_and_never_trains(tmp_path, monkeypatch, capsys):
    import json

    import tracegs.bench.sweep as sweep
    import tracegs.eval.protocol as protocol
    from tracegs.bench.sweep import run_cell
    from tracegs.train.trainer import Trainer

    def no_training(self):
        raise AssertionError("the Hold row must not train")

    scored = []

    def evaluate(run, **kwargs):
        scored.append(kwargs)
        split = {"mae_psnr": 20.0, "ssim": 0.8, "frames": 2, "moving": {"mae_psnr": 15.0}}
        return {"interpolation": split, "extrapolation": split, "motion": kwargs["motion"]}

    monkeypatch.setattr(Trainer, "train", no_training)
    monkeypatch.setattr(protocol, "evaluate_run", evaluate)
    monkeypatch.setattr(
        sweep, "_changed_settings", lambda run, cfg: [] if (run / "eval.json").is_file() else None
    )
    run = tmp_path / "runs" / "scene_TRACE_tiny"
    hold = Cell("scene", "Hold", run, None, run, motion="hold")
    assert run_cell(hold) is None and scored == []  # no TRACE run yet: skipped, nothing trained
    assert "to score with the motion 'hold'" in capsys.readouterr().out
    _finished_run(run, psnr=25.0)
    report_only = Cell("scene", "Hold", run, None, run, motion="hold", train=False)
    assert run_cell(report_only) is None and scored == []  # report-only scores nothing
    row = run_cell(hold)
    assert scored == [{"future_end": None, "out": run / "eval_hold", "motion": "hold"}]
    assert row["variant"] == "Hold" and row["extrap_psnr"] == 20.0 and row["extrap_moving_psnr"] == 15.0
    assert json.loads((run / "eval_hold.json").read_text())["motion"] == "hold"
    assert run_cell(hold)["extrap_psnr"] == 20.0 and len(scored) == 1  # kept while the run is unchanged
    assert run_cell(Cell("scene", "TRACE", run, None, run))["extrap_psnr"] == 25.0  # the TRACE row's own
