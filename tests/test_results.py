"""The results records (docs/results/*.json) and the pages generated from them: docs/RESULTS.md (one
table of every benchmark's headline against its anchor) and docs/results/NAME.md (one per record)."""

import json
from pathlib import Path

import pytest

from tracegs import results

REPO = Path(__file__).resolve().parents[1]


def _record(benchmark="methods", **kw):
    rows = kw.pop("rows", [{"scene": "fan", "variant": "TRACE", "extrap_psnr": 30.6845, "lpips": 0.01234}])
    kw.setdefault("headline", "TRACE 30.68 dB")
    kw.setdefault("anchor", "DefGS 15.87 dB")
    return results.make_record(benchmark, rows, kw.pop("command", "tracegs bench methods --scenes fan"), **kw)


def test_make_write_read_round_trip(tmp_path):
    record = _record(title="TRACE against DefGS", notes="a note")
    assert record["columns"] == ["scene", "variant", "extrap_psnr", "lpips"]
    assert record["machine"] == results.machine_description() and "core" in record["machine"]
    assert len(record["date"]) == 10 and record["date"][4] == "-"
    path = results.write_record(tmp_path / "methods.json", record)
    assert results.read_record(path) == record
    assert list(json.loads(path.read_text())) == list(results.KEYS)


def test_a_record_without_headline_makes_its_pages_and_says_what_is_missing(tmp_path, capsys):
    record = _record(headline=None, anchor=None)
    assert "headline" not in record and "anchor" not in record
    results.write_record(tmp_path / "methods.json", record)
    assert "kept" not in capsys.readouterr().err  # nothing to keep: no record before
    results.write_results_page(tmp_path, tmp_path / "RESULTS.md")
    assert f"| [methods](./methods.md) | {results.MISSING} | – |" in (tmp_path / "RESULTS.md").read_text()
    page = (tmp_path / "methods.md").read_text()
    assert "**No headline and no anchor written yet:** add `headline` (" in page
    with pytest.raises(ValueError, match="methods.json: no 'headline'"):
        results.check_for_pages(record, "methods.json")  # a committed record needs both
    with pytest.raises(ValueError, match="'headline' must be one line"):
        results.validate_record({**_record(), "headline": "two\nlines"})


def test_a_rerun_keeps_the_written_headline_and_anchor(tmp_path, capsys):
    path = tmp_path / "methods.json"
    results.write_record(path, _record(headline="TRACE 30.68 dB", anchor="DefGS 15.87 dB"))
    rerun = _record(headline=None, anchor=None, rows=[{"scene": "fan", "extrap_psnr": 31.0}])
    results.write_record(path, rerun)
    kept = results.read_record(path)
    assert (kept["headline"], kept["anchor"]) == ("TRACE 30.68 dB", "DefGS 15.87 dB")
    assert kept["rows"] == rerun["rows"]
    assert "kept the headline and anchor" in capsys.readouterr().err
    results.write_record(path, _record(headline="TRACE 31.00 dB", anchor=None))  # a new one wins
    assert results.read_record(path)["headline"] == "TRACE 31.00 dB"
    assert results.read_record(path)["anchor"] == "DefGS 15.87 dB"
    path.write_text("{not json")  # an unreadable old record keeps nothing and does not stop the write
    results.write_record(path, rerun)
    assert "headline" not in results.read_record(path)


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


def test_sentences():
    assert results.sentences("") == []
    assert results.sentences("MAE-PSNR 30.6 dB, e.g. fan. `cpu-fast` is the preset. 2 seeds differ.") == [
        "MAE-PSNR 30.6 dB, e.g. fan.",
        "`cpu-fast` is the preset.",
        "2 seeds differ.",
    ]


def test_notes_of_more_than_two_sentences_are_cut_on_the_page(tmp_path):
    results.check_for_pages(_record(notes="One. Two."))
    with pytest.raises(ValueError, match="3 sentences, at most 2"):
        results.check_for_pages(_record(notes="One. Two. Three."), "x.json")
    results.write_record(tmp_path / "a.json", _record(notes="One.  Two.\nThree. Four."))
    results.write_results_page(tmp_path, tmp_path / "RESULTS.md")
    page = (tmp_path / "a.md").read_text()
    assert "\n\nOne. Two.\n\n" in page and "Three" not in page
    notes = results.read_record(tmp_path / "a.json")["notes"]
    assert notes == "One.  Two.\nThree. Four."  # the record keeps them all


def test_pages_of_two_records(tmp_path):
    a = _record(title="Methods on the synthetic scenes", notes="A note on the rows.")
    a["commit"], a["date"] = "abc1234", "2026-11-27"
    b = _record(
        "raster",
        title="Rasteriser speed",
        command="tracegs bench raster --json r.json",
        rows=[{"backend": "native", "ms": 2.8321, "peak_mb": None, "n": 5000}],
        headline="native 2.83 ms",
        anchor="the reference",
    )
    folder = tmp_path / "docs" / "results"
    folder.mkdir(parents=True)
    results.write_record(folder / "b-raster.json", b)
    results.write_record(folder / "a-methods.json", a)
    (folder / "gone.md").write_text("a page whose record was removed")
    out = results.write_results_page(folder, tmp_path / "docs" / "RESULTS.md")
    page = out.read_text()
    assert page.startswith("# Results\n") and "tracegs results" in page
    assert page.index("[methods](results/a-methods.md)") < page.index("[raster](results/b-raster.md)")
    assert "| [methods](results/a-methods.md) | TRACE 30.68 dB | DefGS 15.87 dB | 2026-11-27 |" in page
    assert "| native 2.83 ms | the reference |" in page
    assert sorted(p.name for p in folder.glob("*.md")) == ["a-methods.md", "b-raster.md"]
    methods = (folder / "a-methods.md").read_text()
    assert methods.startswith("# Methods on the synthetic scenes\n")
    assert "**TRACE 30.68 dB** against DefGS 15.87 dB." in methods
    assert f"{a['machine']} · 2026-11-27 · commit abc1234" in methods
    assert "```\ntracegs bench methods --scenes fan\n```" in methods
    assert (
        "| scene | variant | extrap_psnr | lpips |\n|---|---|---|---|\n| fan | TRACE | 30.68 | 0.0123 |"
        in methods
    )
    assert "A note on the rows." in methods and "[RESULTS.md](../RESULTS.md)" in methods
    raster = (folder / "b-raster.md").read_text()
    assert "| native | 2.83 | – | 5000 |" in raster and "commit " in raster
    assert page == results.render_results_page(folder)  # deterministic


def test_the_page_keeps_to_one_screen(tmp_path, monkeypatch):
    for i in range(3):
        results.write_record(tmp_path / f"r{i}.json", _record(f"r{i}"))
    monkeypatch.setattr(results, "MAX_PAGE_LINES", 8)
    with pytest.raises(ValueError, match="more than 8 lines"):
        results.render_results_page(tmp_path)


def test_repository_pages_are_generated_and_short():
    folder = REPO / "docs" / "results"
    page = (REPO / "docs" / "RESULTS.md").read_text(encoding="utf-8")
    assert page == results.render_results_page(folder), "run `tracegs results`"
    assert len(page.splitlines()) <= 80
    records = results.read_records(folder)
    assert {p.stem for p, _ in records} == {p.stem for p in folder.glob("*.md")}
    for path, record in records:
        results.check_for_pages(record, path.name)  # headline, anchor, notes of at most two sentences
        assert f"| {results.format_value(record['headline'])} |" in page
        own = path.with_suffix(".md").read_text(encoding="utf-8")
        assert own == results.render_record(record), f"{path.stem}.md: run `tracegs results`"
        for key in ("machine", "date", "command"):
            assert record[key].strip().splitlines()[0] in own
        assert f"commit {record['commit'] or 'unknown'}" in own
