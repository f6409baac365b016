"""Method/ablation tables: runs are reused when their settings match, shared between identical rows,
and `report_only` trains nothing."""

import json

import pytest
from tests.conftest import write_tiny_scene

from tracegs.bench import ABLATIONS, METHODS, run_variant_table, validation_cut


def test_rows_reuse_and_share_runs(tmp_path, monkeypatch):
    from tracegs import bench_report

    monkeypatch.setattr(bench_report, "RESULTS_DIR", tmp_path / "results")
    monkeypatch.setattr(bench_report, "DEFAULT_PATH", tmp_path / "BENCHMARKS.md")
    out = tmp_path / "bench"
    scenes = (str(write_tiny_scene(tmp_path / "scene", size=32)),)  # LPIPS needs >= 31 px
    rows = run_variant_table(
        "methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", update_docs=False, train=False
    )
    assert rows == []  # nothing finished yet, nothing trained
    assert not (out / "runs").exists()

    rows = run_variant_table("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny", update_docs=False)
    assert [r["variant"] for r in rows] == ["TRACE"]
    assert {"interp_psnr", "extrap_psnr", "train_s", "iterations", "gaussians"} <= set(rows[0])
    checkpoint = out / "runs" / "scene_TRACE_tiny" / "checkpoint.pt"
    stamp = checkpoint.stat().st_mtime_ns

    # the ablation row with the default settings is the TRACE run: reported, not retrained, and
    # stored once, as the methods table's TRACE record, which the ablation table shows as its row
    again = run_variant_table("ablations", {"dt=2": ABLATIONS["dt=2"]}, out, scenes, "tiny", train=False)
    assert [r["extrap_psnr"] for r in again] == [rows[0]["extrap_psnr"]]
    assert checkpoint.stat().st_mtime_ns == stamp
    assert bench_report.load_records("ablations-tiny") == []
    (stored,) = bench_report.load_records("methods-tiny")
    assert (stored["variant"], stored["extrap_psnr"]) == ("TRACE", rows[0]["extrap_psnr"])
    section = (tmp_path / "BENCHMARKS.md").read_text().split("<!-- ablations-tiny:start -->")[1]
    assert f"| scene | dt=2 | {rows[0]['interp_psnr']:.3f} |" in section
    assert "the methods table's TRACE row" in section

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


def test_the_device_is_in_the_rows_command_not_in_the_tables_name(tmp_path, monkeypatch):
    from tracegs import bench_report

    monkeypatch.setattr(bench_report, "RESULTS_DIR", tmp_path / "results")
    monkeypatch.setattr(bench_report, "DEFAULT_PATH", tmp_path / "BENCHMARKS.md")
    out, scenes = tmp_path / "bench", (str(write_tiny_scene(tmp_path / "scene", size=32)),)
    table = ("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny")
    run_variant_table(*table, overrides={"device": "cpu"})
    (stored,) = bench_report.load_records("methods-tiny")
    assert "--device cpu" in stored["command"]
    assert bench_report.load_records("methods-tiny--devicecpu") == []


def test_a_render_time_setting_re_evaluates_a_run_without_retraining(tmp_path, monkeypatch, capsys):
    from tracegs import bench_report

    monkeypatch.setattr(bench_report, "RESULTS_DIR", tmp_path / "results")
    out = tmp_path / "bench"
    scenes = (str(write_tiny_scene(tmp_path / "scene", size=32)),)
    table = ("methods", {"TRACE": METHODS["TRACE"]}, out, scenes, "tiny")
    (row,) = run_variant_table(*table, update_docs=False)
    run = out / "runs" / "scene_TRACE_tiny"
    trained = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    scored = (run / "eval.json").stat().st_mtime_ns
    # a setting read only when rendering: the finished run is scored again, not trained again
    later = {"dynamic__handover_frames": 0.0}
    assert run_variant_table(*table, overrides=later, train=False) == []  # report-only computes nothing
    assert "dynamic.handover_frames" in capsys.readouterr().out
    (again,) = run_variant_table(*table, overrides=later, update_docs=False)
    assert not run.with_name(run.name + ".previous").exists()
    assert json.loads((run / "log.jsonl").read_text().splitlines()[-1]) == trained  # no step was added
    assert json.loads((run / "config.json").read_text())["dynamic"]["handover_frames"] == 0.0
    assert (run / "eval.json").stat().st_mtime_ns != scored
    assert again["train_s"] == row["train_s"]
    # a training setting: set aside and trained afresh
    run_variant_table(*table, overrides={"dynamic__dt_frames": 3.0}, update_docs=False)
    assert run.with_name(run.name + ".previous").is_dir()


def test_merge_records_keeps_other_rows_and_replaces_same_key(tmp_path):
    from tracegs.bench_report import merge_records

    merge_records("t", [{"scene": "a", "variant": "TRACE", "psnr": 1.0}], ("scene", "variant"), tmp_path)
    merge_records("t", [{"scene": "b", "variant": "TRACE", "psnr": 2.0}], ("scene", "variant"), tmp_path)
    table = merge_records(
        "t", [{"scene": "a", "variant": "TRACE", "psnr": 3.0}], ("scene", "variant"), tmp_path
    )
    assert [(r["scene"], r["psnr"]) for r in table] == [("a", 3.0), ("b", 2.0)]  # replaced in its place


def test_merge_records_keeps_the_note_of_a_row_remade_from_the_same_run(tmp_path):
    from tracegs.bench_report import merge_records

    row = {"scene": "a", "variant": "TRACE", "psnr": 1.0, "command": "first"}
    merge_records("t", [row | {"note": "inflated"}], ("scene", "variant"), tmp_path)
    table = merge_records("t", [row | {"command": "again"}], ("scene", "variant"), tmp_path)
    assert [(r["command"], r.get("note")) for r in table] == [("first", "inflated")]
    table = merge_records("t", [row | {"psnr": 2.0, "command": "rerun"}], ("scene", "variant"), tmp_path)
    assert [(r["command"], r.get("note"), r["psnr"]) for r in table] == [("rerun", None, 2.0)]


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
        update_docs=False,
        validation=0.8,
    )
    assert [(r["t_cut"], r["t_end"]) for r in rows] == [(0.5, 0.75)]
    run = out / "runs" / "scene_TRACE_tiny_val0.8"
    assert json.loads((run / "config.json").read_text())["t_train_end"] == 0.5
    result = json.loads((run / "eval.json").read_text())
    assert result["future_end"] == 0.75 and result["extrapolation"]["frames"] == 2  # 2 training cameras
    assert rows[0]["val_future_psnr"] == result["extrapolation"]["mae_psnr"]
    assert not (out / "runs" / "scene_TRACE_tiny").exists()  # the test-protocol run is a separate folder


def test_tables_show_rows_scene_by_scene_in_the_variant_order():
    from tracegs.bench import variant_table_markdown

    def row(scene, variant):
        return {
            "scene": scene,
            "variant": variant,
            "psnr": 1.0,
            "ms_per_it": {"fields": 1.0},
            "command": "c",
            "machine": "m",
        }

    records = [
        row("b", "DefGS"),
        row("a", "TRACE"),
        row("b", "TRACE"),
        row("a", "mine"),
        row("b", "TRACE_4dgs"),
    ]
    text = variant_table_markdown("methods", "tiny", 32, records)
    quality = [
        line.split(" | ")[:2] for line in text.split("Time per")[0].splitlines() if line.startswith("| ")
    ]
    assert quality[1:] == [
        ["| b", "TRACE"],
        ["| b", "TRACE_4dgs"],
        ["| b", "DefGS"],
        ["| a", "TRACE"],
        ["| a", "mine"],
    ]


def test_cli_ablations_take_our_options_as_rows_on_request(tmp_path, capsys):
    from tracegs.bench import OPTIONS
    from tracegs.cli import main

    scene = str(write_tiny_scene(tmp_path / "scene", size=32))
    common = ["bench", "ablations", "--scenes", scene, "--out", str(tmp_path / "bench"), "--report-only"]
    main([*common, "--variants", "skip static", "--preset", "tiny"])  # known: nothing finished, no rows
    assert "no finished run" in capsys.readouterr().out
    assert not set(OPTIONS) & set(ABLATIONS)  # never a default row of the paper's table
    with pytest.raises(SystemExit, match="skip static"):  # the error lists it among the choices
        main([*common, "--variants", "no such row"])
