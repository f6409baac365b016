"""The README's demo timed on this machine, as a row of the `demo` record.

`tracegs demo` (the built-in `fan` scene synthesised, trained with `cpu-fast`, evaluated, a video
rendered) runs in a process of its own; the row takes the run's training time and fields' dtype
(its `summary.json`), the extrapolation MAE-PSNR (its `eval.json`) and the whole command's time. On
an AVX2-only laptop that is what the README's first command costs there. `--isa avx2` holds this CPU
to an AVX2-only CPU's code paths (ATen, oneDNN, MKL, the extensions built for x86-64-v3: fp32 fields),
which approximates such a laptop on this CPU's cores but is not one: its row says so.

With `--json docs/results/demo.json` the row goes into the record (`merge_row`): it replaces the row of
the same CPU and fields, unless that row's code is marked as a baseline ("before ..."), which the
record's notes compare with; every other row stays. Run it alone on the machine, after
`bash scripts/install.sh` (the extensions built), then `tracegs results`; the notes speak of the rows
they compare: read them again. Usage:
.venv/bin/python benchmarks/demo_time.py [--isa native|avx2] [--out runs/demo_time] [--json docs/results/demo.json]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

from tracegs.machine import ISA_ENVIRONMENTS
from tracegs.results import (
    current_commit,
    machine_description,
    make_record,
    page_notes,
    read_record,
    write_record,
)

COLUMNS = ["cpu", "fields", "train_s", "train_min", "command_min", "extrap_mae_psnr", "code", "date"]
TITLE = "The README's demo (`fan`, `cpu-fast`): training time on 2 CPU cores, per CPU"
COMMAND = "bash scripts/install.sh && .venv/bin/tracegs demo"


def cpu_label(isa: str, description: str | None = None) -> str:
    """The row's CPU: this machine's model and extensions (its core count where it is not 2), and
    "limited to AVX2 code" when the demo ran held to AVX2."""
    cores, _, cpu = (description or machine_description()).partition(", ")
    label = cpu if cores == "2 cores" else f"{cpu}, {cores}"
    return label + (" limited to AVX2 code" if isa == "avx2" else "")


def demo_row(run: Path, isa: str, command_seconds: float, code: str | None, date: str) -> dict:
    """The row of a finished demo run folder ``run`` (its summary.json and eval.json)."""
    summary = json.loads((run / "summary.json").read_text())
    metrics = json.loads((run / "eval.json").read_text())
    seconds = float(summary["train_seconds"])
    machine = summary.get("machine")  # (a line of text in the summaries of earlier versions)
    return {
        "cpu": cpu_label(isa, machine["description"] if isinstance(machine, dict) else machine),
        "fields": summary.get("fields_dtype", "unknown"),  # (summaries before it was recorded)
        "train_s": round(seconds, 1),
        "train_min": f"{seconds / 60:.1f}",
        "command_min": f"{command_seconds / 60:.1f} (no install)",
        "extrap_mae_psnr": round(float(metrics["extrapolation"]["mae_psnr"]), 2),
        "code": code or "unknown",
        "date": date,
    }


def merge_row(rows: list[dict], new: dict) -> list[dict]:
    """``rows`` with ``new`` in place of the row of the same CPU and fields (a baseline row, its code
    marked "before", stays), or after them."""
    merged, placed = [], False
    for row in rows:
        same = row.get("cpu") == new["cpu"] and row.get("fields") == new["fields"]
        if same and "before" not in str(row.get("code", "")):
            if not placed:
                merged.append(new)
                placed = True
            continue
        merged.append(row)
    return merged if placed else [*merged, new]


def demo_record(old: dict | None, row: dict) -> dict:
    """The demo record with ``row`` merged into the rows of the ``old`` record (``merge_row``), whose
    notes it keeps (at most two sentences, as a committed record has them)."""
    rows = merge_row(old["rows"] if old else [], row)
    notes = page_notes(old.get("notes")) if old else None
    record = make_record("demo", rows, COMMAND, title=TITLE, columns=COLUMNS, notes=notes)
    record["machine"] = "2 cores each, the CPUs of the rows"
    return record


def time_demo(out: Path, isa: str) -> float:
    """``tracegs demo --out out`` in a new process held to ``isa``; its wall time in seconds."""
    shutil.rmtree(out, ignore_errors=True)
    command = [sys.executable, "-m", "tracegs", "demo", "--out", str(out)]
    start = time.perf_counter()
    subprocess.run(command, env={**os.environ, **ISA_ENVIRONMENTS[isa]}, check=True)
    return time.perf_counter() - start


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--isa", choices=tuple(ISA_ENVIRONMENTS), default="native", help="this CPU's code, or AVX2's"
    )
    ap.add_argument("--out", type=Path, default=Path("runs/demo_time"), help="the demo's folder (replaced)")
    ap.add_argument("--json", type=Path, default=None, help="the demo record to put the row in")
    args = ap.parse_args()
    seconds = time_demo(args.out, args.isa)
    today = datetime.datetime.now(datetime.timezone.utc).date().isoformat()
    row = demo_row(args.out / "trace", args.isa, seconds, current_commit(), today)
    print(json.dumps(row))
    if args.json:
        old = read_record(args.json) if args.json.is_file() else None
        write_record(args.json, demo_record(old, row))
        print(f"{args.json}: the row is in; its notes compare rows by their numbers: read them again")


if __name__ == "__main__":
    main()
