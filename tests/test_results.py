"""The results records (docs/results/*.json) and the page generated from them (docs/RESULTS.md)."""

import json
from pathlib import Path

import pytest

from tracegs import results

REPO = Path(__file__).resolve().parents[1]


def _record(benchmark="methods", **kw):
    rows = kw.pop("rows", [{"scene": "fan", "variant": "TRACE", "extrap_psnr": 30.6845, "lpips": 0.01234}])
    record = results.make_record(
        benchmark, rows, kw.pop("command", "tracegs bench methods --scenes fan"), **kw
    )
    return record


def test_make_write_read_round_trip(tmp_path):
    record = _record(title="TRACE against DefGS", notes="a note")
    assert record["columns"] == ["scene", "variant", "extrap_psnr", "lpips"]
    assert record["machine"] == results.machine_description() and "core" in record["machine"]
    assert len(record["date"]) == 10 and record["date"][4] == "-"
    path = results.write_record(tmp_path / "methods.json", record)
    assert results.read_record(path) == record
    assert list(json.loads(path.read_text())) == list(results.KEYS)


def test_read_record_missing_keys_names_the_file(tmp_path):
    path = tmp_path / "old-format.json"
    path.write_text(json.dumps({"benchmark": "methods", "rows": []}))
    with pytest.raises(ValueError, match="old-format.json") as err:
        results.read_record(path)
    assert "command" in str(err.value)
    path.write_text(json.dumps([{"scene": "fan"}]))  # a list of rows, the old layout
    with pytest.raises(ValueError, match="old-format.json"):
        results.read_record(path)


def test_current_commit_outside_a_repository_is_none(tmp_path):
    assert results.current_commit(tmp_path) is None


def test_page_of_two_records(tmp_path):
    a = _record(title="Methods on the synthetic scenes")
    a["commit"], a["date"] = "abc1234", "2026-11-27"
    b = _record(
        "raster",
        title="Rasteriser speed",
        command="tracegs bench raster --json r.json",
        rows=[{"backend": "native", "ms": 2.8321, "peak_mb": None, "n": 5000}],
    )
    results.write_record(tmp_path / "b-raster.json", b)
    results.write_record(tmp_path / "a-methods.json", a)
    page = results.render_results_page(tmp_path)
    assert page.startswith("# Results\n") and "tracegs results" in page
    assert page.index("## Methods on the synthetic scenes") < page.index("## Rasteriser speed")
    assert "```\ntracegs bench methods --scenes fan\n```" in page
    assert "```\ntracegs bench raster --json r.json\n```" in page
    assert f"{a['machine']} · 2026-11-27 · abc1234" in page
    assert (
        "| scene | variant | extrap_psnr | lpips |\n|---|---|---|---|\n| fan | TRACE | 30.68 | 0.0123 |"
        in page
    )
    assert "| native | 2.83 | – | 5000 |" in page
    assert page == results.render_results_page(tmp_path)  # deterministic


def test_repository_page_is_generated_and_short():
    page = results.render_results_page(REPO / "docs" / "results")
    assert page == (REPO / "docs" / "RESULTS.md").read_text(encoding="utf-8"), "run `tracegs results`"
    assert len(page.splitlines()) < 555  # one table per benchmark, 25 of them
