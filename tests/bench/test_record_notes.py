"""Every benchmark writer's notes pass `results.check_for_pages` as written: at most two sentences, so
a rerun's record is ready to commit (what each row differs in lives in its columns)."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

from tracegs import results
from tracegs.bench import raster

ROOT = Path(__file__).parents[2]


def _script(name: str):
    spec = importlib.util.spec_from_file_location(f"bench_{name}", ROOT / "benchmarks" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


appearance_ceiling, continual, demo_time = map(_script, ("appearance_ceiling", "continual", "demo_time"))
fields_floor, horizon, lpips_calibration = map(_script, ("fields_floor", "horizon", "lpips_calibration"))
nonconstant_forces, panoptic, segmentation = map(_script, ("nonconstant_forces", "panoptic", "segmentation"))
static_quality, training_speed = map(_script, ("static_quality", "training_speed"))
ball, moving_regions = _script("ball"), _script("moving_regions")
simulators, import_record = _script("simulators"), _script("import_record")

NOTE = "Round 0 trains 1000 static + 4000 dynamic steps, each later round 1000."
DTYPE_ROW = {"what": training_speed.DTYPE_ROWS, "setting": "bf16, 2 thread(s)"}
NOTES = {
    "appearance_ceiling": appearance_ceiling.record_notes(12),
    "ball": ball.NOTES,
    "moving_regions": moving_regions.NOTES,
    "simulators": simulators.NOTES,
    "import_record": import_record.NOTES,
    "continual": continual.record_notes(),
    "continual, --note": continual.record_notes(NOTE),
    "fields_floor": fields_floor.record_notes(6),
    "horizon": horizon.record_notes(2.0, 4, Path("docs/figures/horizon")),
    "horizon, 2.5x": horizon.record_notes(2.5, 3, Path("/tmp/figures.v2")),
    "lpips_calibration": lpips_calibration.record_notes("alexnet.pkl"),
    "nonconstant_forces": nonconstant_forces.NOTES,
    "panoptic": panoptic.record_notes(),
    "panoptic, --note": panoptic.record_notes("TRACE is the capture preset as it ships."),
    "segmentation": segmentation.record_notes(),
    "segmentation, --note": segmentation.record_notes("Panoptic's masks are foreground / background."),
    "static_quality": static_quality.record_notes("fan", 40),
    "training_speed": training_speed.record_notes(Path("runs/demo/trace"), [{"what": "training step"}]),
    "training_speed, bf16": training_speed.record_notes(Path("runs/demo/trace"), [DTYPE_ROW]),
    "raster": raster.record_notes(("native",)),
    "raster, --isa native avx2": raster.record_notes(("native", "avx2")),
    "raster, --isa avx2": raster.record_notes(("avx2",)),
}


@pytest.mark.parametrize("name", NOTES)
def test_the_notes_a_writer_writes_are_ready_to_commit(name):
    record = {"headline": "h", "anchor": "a", "notes": NOTES[name]}
    assert results.check_for_pages(record, name) is record
    assert 1 <= len(results.sentences(NOTES[name])) <= results.MAX_NOTE_SENTENCES


def test_every_writer_of_notes_is_held_here():
    writers = [*(ROOT / "benchmarks").glob("*.py"), *(ROOT / "src" / "tracegs" / "bench").glob("*.py")]
    writing = {p.stem for p in writers if re.search(r"\bnotes\s*=", p.read_text())}
    held = {name.split(",")[0] for name in NOTES} | {"demo_time"}
    assert writing <= held, f"notes written by {sorted(writing - held)}: add them to NOTES above"


@pytest.mark.parametrize("module", [continual, panoptic, segmentation], ids=lambda m: m.__name__)
def test_a_note_of_more_than_one_sentence_is_refused(module):
    with pytest.raises(ValueError, match="one sentence"):
        module.record_notes("One caveat. And a story.")


def test_the_demo_record_keeps_the_notes_it_replaces_within_two_sentences():
    old = results.read_record(ROOT / "docs" / "results" / "demo.json")
    row = {"cpu": "AMD EPYC (AVX2)", "fields": "fp32", "code": "abc1234", "train_s": 1.0}
    record = demo_time.demo_record(old, row)
    assert record["notes"] == old["notes"] and row in record["rows"]
    long = demo_time.demo_record({**old, "notes": "One. Two. Three."}, row)
    assert long["notes"] == "One. Two."
    assert "notes" not in demo_time.demo_record(None, row)


def test_nonconstant_forces_reads_each_rows_commit_and_machine_back():
    row = {"scene": "spring", "variant": "DefGS", "extrap_psnr": 24.9}
    record = {
        "commit": "bbb2222",
        "machine": "2 cores, AMD EPYC (AVX2)",
        "rows": [
            {**row, "commit": "aaa1111", "machine": "2 cores, Intel Xeon (AMX-BF16)"},
            {**row, "scene": "pendulum", "commit": "ccc3333"},  # (a row of a record before the column)
            {**row, "scene": "brake"},
        ],
    }
    kept = nonconstant_forces.kept_rows(json.loads(json.dumps(record)))
    assert kept[("spring", "DefGS")]["machine"] == "2 cores, Intel Xeon (AMX-BF16)"
    assert kept[("pendulum", "DefGS")]["machine"] is None
    assert kept[("brake", "DefGS")] == {
        **row,
        "scene": "brake",
        "commit": "bbb2222",
        "machine": record["machine"],
    }
    assert all(set(r) <= set(nonconstant_forces.COLUMNS) for r in kept.values())


def test_segmentation_rows_carry_what_the_notes_used_to_say():
    scores = {m: 0.5 for m in segmentation.SHOWN}
    report = {"k": 3, "scores": {"training_times": scores, "future_times": scores}}
    report["seconds"] = {"segment": 1.23, "score": 40.0}
    facts = {
        "trained": "`--preset cpu-fast`, 256 px",
        "ground truth": segmentation.ground_truth([["a", "b"]]),
    }
    (row,) = segmentation.rows_of("fan", "TRACE", "given", report, **facts)
    assert list(row) == segmentation.COLUMNS
    assert row["ground truth"] == "parts (a, b merged)" and row["segment s"] == 1.2
    assert segmentation.ground_truth([]) == "parts"


def test_the_moving_regions_row_reads_tracegs_evals_moving_entries():
    def split(whole, moving, share=None):
        return {"mae_psnr": whole, "moving": {"mae_psnr": moving, "pixel_share": share}}

    trace = {"extrapolation": split(30.123, 22.456, 0.08), "interpolation": split(29.0, 25.0)}
    hold = {"extrapolation": split(25.0, 15.5)}
    row = moving_regions.row("fan", trace, hold)
    assert list(row) == moving_regions.COLUMNS
    assert row == {"scene": "fan", "trace_extrap": 30.12, "trace_extrap_moving": 22.46, "hold_extrap_moving": 15.5,
                   "trace_interp": 29.0, "trace_interp_moving": 25.0, "moving_share": 0.08}  # fmt: skip
    assert (
        moving_regions.row("x", {**trace, "interpolation": {"mae_psnr": 1.0}}, hold)["trace_interp_moving"]
        is None
    )
