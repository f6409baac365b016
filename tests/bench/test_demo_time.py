"""benchmarks/demo_time.py: the demo's row from a run folder, and where it goes in the record."""

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).parents[2] / "benchmarks" / "demo_time.py"
spec = importlib.util.spec_from_file_location("demo_time", SCRIPT)
demo_time = importlib.util.module_from_spec(spec)
spec.loader.exec_module(demo_time)


def _row(cpu: str, fields: str, code: str, train_s: float = 1.0) -> dict:
    return {"cpu": cpu, "fields": fields, "code": code, "train_s": train_s}


def test_a_new_row_replaces_its_cpu_and_fields_but_not_a_baseline():
    rows = [
        _row("EPYC (AVX2)", "fp32", "04c4926 (before the speed work)", 1848),
        _row("EPYC (AVX2)", "fp32", "76216af", 800),
        _row("EPYC (AVX2)", "bf16", "76216af", 700),
        _row("Xeon (AMX-BF16)", "bf16", "4233a3d", 652),
    ]
    new = _row("EPYC (AVX2)", "fp32", "abc1234", 750)
    merged = demo_time.merge_row(rows, new)
    assert merged == [rows[0], new, rows[2], rows[3]]  # (in the replaced row's place)
    other = _row("EPYC (AVX2, AVX-512)", "fp32", "abc1234")
    assert demo_time.merge_row(rows, other) == [*rows, other]
    only_baseline = demo_time.merge_row(rows[:1], new)
    assert only_baseline == [rows[0], new]


@pytest.mark.parametrize(
    "machine",
    [{"description": "2 cores, AMD EPYC (AVX2)", "cores": 2, "fast_bf16": False}, "2 cores, AMD EPYC (AVX2)"],
    ids=["record", "earlier-text"],
)
def test_the_row_comes_from_the_runs_summary_and_eval(tmp_path, machine):
    run = tmp_path / "trace"
    run.mkdir()
    summary = {"train_seconds": 454.04, "fields_dtype": "fp32", "machine": machine}
    (run / "summary.json").write_text(json.dumps(summary))
    (run / "eval.json").write_text(json.dumps({"extrapolation": {"mae_psnr": 30.5449}}))
    row = demo_time.demo_row(run, "native", 600.0, "abc1234", "2026-12-06")
    assert row == {
        "cpu": "AMD EPYC (AVX2)",
        "fields": "fp32",
        "train_s": 454.0,
        "train_min": "7.6",
        "command_min": "10.0 (no install)",
        "extrap_mae_psnr": 30.54,
        "code": "abc1234",
        "date": "2026-12-06",
    }
    assert list(row) == demo_time.COLUMNS


def test_the_cpu_label_says_the_cores_other_than_two_and_a_held_isa():
    assert demo_time.cpu_label("native", "2 cores, Intel Xeon (AVX2)") == "Intel Xeon (AVX2)"
    assert demo_time.cpu_label("native", "8 cores, Intel Xeon (AVX2)") == "Intel Xeon (AVX2), 8 cores"
    held = demo_time.cpu_label("avx2", "2 cores, AMD EPYC (AVX2, AVX-512)")
    assert held == "AMD EPYC (AVX2, AVX-512) limited to AVX2 code"
