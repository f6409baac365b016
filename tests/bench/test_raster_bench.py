"""`tracegs bench raster --isa native avx2`: each instruction set's rows from a process of its own."""

from __future__ import annotations

import json

import pytest

from tracegs.bench.raster import run_raster_bench
from tracegs.machine import this_machine
from tracegs.render.native import is_available as native_available


def test_the_avx2_rows_run_in_a_child_and_sit_beside_the_native_ones(tmp_path):
    if not native_available() or "avx2" not in this_machine().flags:
        pytest.skip("needs the native rasteriser on a CPU with AVX2")
    path = tmp_path / "raster.json"
    rows = run_raster_bench(
        path, widths=(48,), counts=(300,), repeats=1, isas=("native", "avx2"), device="cpu"
    )
    assert [(r["isa"], r["backend"]) for r in rows] == [
        ("native", "native"),
        ("native", "reference"),
        ("avx2", "native"),
    ]
    assert all(r["ms_forward_backward"] > 0 for r in rows)
    record = json.loads(path.read_text())
    assert "--isa native avx2" in record["command"] and "avx2_ms_forward_backward" in record["columns"]
    native, reference = record["rows"]  # (the avx2 times beside the native ones)
    assert native["avx2_ms_forward_backward"] == rows[2]["ms_forward_backward"]
    assert "avx2_ms_forward" not in reference and native["speed-up fwd+bwd"] is not None


def test_an_unknown_isa_is_named():
    with pytest.raises(ValueError, match="sse9"):
        run_raster_bench(None, widths=(48,), counts=(10,), repeats=1, isas=("native", "sse9"), device="cpu")
