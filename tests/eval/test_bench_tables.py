"""Method/ablation tables: runs are reused when their settings match, shared between identical rows,
`report_only` trains nothing, and with ``json_path`` the rows are written as a results record."""

import json

import pytest
from tests.conftest import write_tiny_scene

from tracegs.bench import ABLATIONS, METHODS, run_variant_table, validation_cut
from tracegs.results import read_record


def test_rows_reuse_and_share_runs(tmp_path):
    out = tmp_path / "bench"
    scenes = (str(write_tiny_scene(tmp_path / "scene", size=32)),)  # LPIPS needs >= 31 px
    methods = tmp_path / "results" / "methods.json"
    rows = run_variant_table("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", train=False)
    assert rows == []  # nothing finished yet, nothing trained
    assert not (out / "runs").exists()
    rows = run_variant_table(
        "methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", train=False, json_path=methods
    )
    assert rows == [] and not methods.exists()  # no rows: no record

    rows = run_variant_table("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", json_path=methods)
    assert [r["variant"] for r in rows] == ["TRACE"]
    assert {"interp_psnr", "extrap_psnr", "train_s", "iterations", "gaussians"} <= set(rows[0])
    checkpoint = out / "runs" / "scene_TRACE_tiny" / "checkpoint.pt"
    stamp = checkpoint.stat().st_mtime_ns
    stored = read_record(methods)
    assert stored["benchmark"] == "methods" and "tracegs bench methods" in stored["command"]
    assert [(r["scene"], r["variant"], r["extrap_psnr"]) for r in stored["rows"]] == [
        ("scene", "TRACE", rows[0]["extrap_psnr"])
    ]

    # the ablation row with the default settings is the TRACE run: reported, not retrained
    ablations = tmp_path / "results" / "ablations.json"
    again = run_variant_table(
        "ablations", {"dt=2": ABLATIONS["dt=2"]}, out, scenes, "tiny", train=False, json_path=ablations
    )
    assert [(r["variant"], r["extrap_psnr"]) for r in again] == [("dt=2", rows[0]["extrap_psnr"])]
    assert checkpoint.stat().st_mtime_ns == stamp
    (row,) = read_record(ablations)["rows"]
    assert (row["variant"], row["interp_psnr"], row["extrap_psnr"]) == (
        "dt=2",
        rows[0]["interp_psnr"],
        rows[0]["extrap_psnr"],
    )

    # a run made before a setting existed reads it as its default and is still the same run; a run
    # made with another value of a setting is not
    config_path = out / "runs" / "scene_TRACE_tiny" / "config.json"
    saved = json.loads(config_path.read_text())
    del saved["init_box"]
    config_path.write_text(json.dumps(saved))
    again = run_variant_table("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", train=False)
    assert [r["extrap_psnr"] for r in again] == [rows[0]["extrap_psnr"]]
    saved["init_box"] = "origin"
    config_path.write_text(json.dumps(saved))
    assert run_variant_table("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", train=False) == []


def test_the_device_is_in_the_records_command_not_in_the_tables_name(tmp_path):
    out, scenes = tmp_path / "bench", (str(write_tiny_scene(tmp_path / "scene", size=32)),)
    table = ("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny")
    path = tmp_path / "methods.json"
    run_variant_table(*table, overrides={"device": "cpu", "stage2.dt_frames": 2.0}, json_path=path)
    stored = read_record(path)
    assert "--device cpu" in stored["command"] and "--stage2.dt-frames 2.0" in stored["command"]
    assert stored["benchmark"] == "methods" and "cpu" not in stored["title"]
    assert [r["variant"] for r in stored["rows"]] == ["TRACE"]


def test_a_render_time_setting_re_evaluates_a_run_without_retraining(tmp_path, capsys):
    out = tmp_path / "bench"
    scenes = (str(write_tiny_scene(tmp_path / "scene", size=32)),)
    table = ("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny")
    (row,) = run_variant_table(*table)
    run = out / "runs" / "scene_TRACE_tiny"
    trained = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    scored = (run / "eval.json").stat().st_mtime_ns
    # a setting read only when rendering: the finished run is scored again, not trained again
    later = {"extrapolation.handover_frames": 0.0}
    assert run_variant_table(*table, overrides=later, train=False) == []  # report-only computes nothing
    assert "extrapolation.handover_frames" in capsys.readouterr().out
    (again,) = run_variant_table(*table, overrides=later)
    assert not run.with_name(run.name + ".previous").exists()
    assert json.loads((run / "log.jsonl").read_text().splitlines()[-1]) == trained  # no step was added
    assert json.loads((run / "config.json").read_text())["extrapolation"]["handover_frames"] == 0.0
    assert (run / "eval.json").stat().st_mtime_ns != scored
    assert again["train_s"] == row["train_s"]
    # a training setting: set aside and trained afresh
    run_variant_table(*table, overrides={"stage2.dt_frames": 3.0})
    assert run.with_name(run.name + ".previous").is_dir()


def test_validation_table_trains_to_the_cut_and_scores_the_rest_of_the_training_span(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", n_cams=3, n_times=5, size=32)  # times 0, 0.25 ... 1
    assert validation_cut(scene, 0.8) == (0.5, 0.75)  # the last time at or before 0.6
    assert validation_cut(scene, 0.5, t_end=1.0) == (0.5, 1.0)
    for fraction in (0.2, 1.0):  # one training time before the cut; no future left
        with pytest.raises(ValueError, match="validation"):
            validation_cut(scene, fraction)
    out = tmp_path / "bench"
    rows = run_variant_table(
        "ablations",
        {"dt=2": ABLATIONS["dt=2"]},
        out,
        (str(scene),),
        "tiny",
        validation=0.8,
    )
    assert [(r["t_cut"], r["t_end"]) for r in rows] == [(0.5, 0.75)]
    run = out / "runs" / "scene_TRACE_tiny_val0.8"
    assert json.loads((run / "config.json").read_text())["t_train_end"] == 0.5
    result = json.loads((run / "eval.json").read_text())
    assert result["future_end"] == 0.75 and result["extrapolation"]["frames"] == 2  # 2 training cameras
    assert rows[0]["val_future_psnr"] == result["extrapolation"]["mae_psnr"]
    assert not (out / "runs" / "scene_TRACE_tiny").exists()  # the test-protocol run is a separate folder


def test_rows_and_their_record_go_scene_by_scene_in_the_variant_order(tmp_path):
    out = tmp_path / "bench"
    scenes = tuple(str(write_tiny_scene(tmp_path / name, size=32)) for name in ("b", "a"))
    variants = {"TRACE": METHODS["TRACE"], "DefGS": METHODS["DefGS"]}
    path = tmp_path / "methods.json"
    rows = run_variant_table("methods", variants, out, scenes, "tiny", json_path=path)
    order = [("b", "TRACE"), ("b", "DefGS"), ("a", "TRACE"), ("a", "DefGS")]
    assert [(r["scene"], r["variant"]) for r in rows] == order
    stored = read_record(path)
    assert [(r["scene"], r["variant"]) for r in stored["rows"]] == order
    # the record's rows are flat: the per-part timings are columns of their own, not shown
    assert "ms_per_it" not in stored["columns"] and stored["columns"][:2] == ["scene", "variant"]
    for row, flat in zip(rows, stored["rows"], strict=True):
        assert flat["extrap_psnr"] == row["extrap_psnr"]
        assert {f"ms_{k}": v for k, v in row["ms_per_it"].items()}.items() <= flat.items()
    assert stored["title"] == "methods (tiny, 128 px)"


def test_cli_ablations_take_our_options_as_rows_on_request(tmp_path, capsys):
    from tracegs.bench import OPTIONS
    from tracegs.cli import main

    scene = str(write_tiny_scene(tmp_path / "scene", size=32))
    common = ["bench", "ablations", "--scenes", scene, "--out", str(tmp_path / "bench"), "--report-only"]
    main([*common, "--variants", "skip static", "--preset", "tiny"])  # known: nothing finished, no rows
    assert "no finished run" in capsys.readouterr().out
    assert not set(OPTIONS) & set(ABLATIONS)  # never a default row of the paper's table
    with pytest.raises(SystemExit) as exit_:
        main([*common, "--variants", "no such row"])
    assert exit_.value.code == 1
    assert "skip static" in capsys.readouterr().err  # the one-line error lists it among the choices


def test_a_row_that_differs_after_training_reuses_the_trace_training(tmp_path, monkeypatch):
    from tracegs.train.trainer import Trainer

    out = tmp_path / "bench"
    scenes = (str(write_tiny_scene(tmp_path / "scene", size=32)),)
    first = run_variant_table("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny")

    def no_training(self):
        raise AssertionError("a row that differs only after training must not train")

    monkeypatch.setattr(Trainer, "train_step", no_training)
    variant = {"TRACE joint laws": METHODS["TRACE joint laws"]}
    rows = run_variant_table("methods", variant, out, scenes, "tiny")
    trace, joint = (out / "runs" / f"scene_{slug}_tiny" for slug in ("TRACE", "TRACE_joint_laws"))
    assert [r["variant"] for r in rows] == ["TRACE joint laws"]
    assert rows[0]["train_s"] == first[0]["train_s"] and rows[0]["iterations"] == first[0]["iterations"]
    assert not joint.with_name(joint.name + ".previous").exists()
    assert json.loads((joint / "config.json").read_text())["extrapolation"]["joint_laws"] is True
    assert json.loads((trace / "config.json").read_text())["extrapolation"]["joint_laws"] is False


def test_cli_bench_trains_its_rows_with_the_seed_asked(tmp_path, monkeypatch):
    import tracegs.bench.command as command
    from tracegs.cli import main

    seen = {}
    monkeypatch.setattr(command, "run_variant_table", lambda *a, **k: seen.update(overrides=a[6]) or [])
    main(["bench", "ablations", "--out", str(tmp_path / "b"), "--seed", "3", "--variants", "dt=2"])
    assert seen["overrides"] == {"seed": 3}
    main(["bench", "ablations", "--out", str(tmp_path / "b"), "--variants", "dt=2"])
    assert seen["overrides"] == {}  # the preset's seed
