"""Write benchmark results into docs/BENCHMARKS.md, one named section per benchmark.

Each benchmark owns the text between ``<!-- NAME:start -->`` and ``<!-- NAME:end -->``; re-running a
benchmark replaces its own section and leaves the others untouched.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import platform
import re
from pathlib import Path

import torch

DEFAULT_PATH = Path(__file__).resolve().parents[2] / "docs" / "BENCHMARKS.md"
RESULTS_DIR = DEFAULT_PATH.parent / "results"
"""Raw benchmark records, one JSON file per table, so that a table keeps the rows of earlier runs
(run folders are not part of the repository; a table run on one scene must not erase the others)."""


def cpu_name() -> str:
    """The CPU's model name (``/proc/cpuinfo``), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_description() -> str:
    """One line naming the CPU, core count, torch version and date, for every benchmark table."""
    cpu = cpu_name()
    gpu = f", GPU {torch.cuda.get_device_name(0)}" if torch.cuda.is_available() else ""
    threads = torch.get_num_threads()
    return (
        f"{cpu}, {os.cpu_count()} cores, {threads} torch thread{'s' if threads != 1 else ''}{gpu}, "
        f"torch {torch.__version__}, {_dt.date.today().isoformat()}"
    )


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    """Render ``rows`` as a GitHub markdown table with the given column order."""

    def fmt(v):
        if isinstance(v, float):
            return f"{v:.3f}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v)

    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in columns) + " |" for r in rows]
    return "\n".join(lines)


def update_section(name: str, body: str, path: str | Path | None = None) -> Path:
    """Replace (or append) the section ``name`` of the benchmarks file with ``body``; atomic write."""
    path = Path(path) if path is not None else DEFAULT_PATH
    start, end = f"<!-- {name}:start -->", f"<!-- {name}:end -->"
    text = (
        path.read_text()
        if path.exists()
        else "# Benchmarks\n\nEvery number below comes from a run of the command shown with it.\n"
    )
    block = f"{start}\n{body.strip()}\n{end}"
    pattern = re.compile(re.escape(start) + r".*?" + re.escape(end), re.S)
    text = (
        pattern.sub(lambda _: block, text) if pattern.search(text) else text.rstrip() + "\n\n" + block + "\n"
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
    return path


def _measurements(record: dict) -> dict:
    """A record without its provenance (the command, machine and note that describe the run)."""
    return {k: v for k, v in record.items() if k not in ("command", "machine", "note")}


def load_records(name: str, folder: str | Path | None = None) -> list[dict]:
    """The records stored in ``folder/NAME.json`` (default ``docs/results``); [] if there are none."""
    path = Path(folder if folder is not None else RESULTS_DIR) / f"{name}.json"
    stored = json.loads(path.read_text()) if path.is_file() else []
    if not isinstance(stored, list):
        raise ValueError(f"{path}: expected a JSON list of benchmark records")
    return stored


def merge_records(
    name: str, records: list[dict], keys: tuple[str, ...], folder: str | Path | None = None
) -> list[dict]:
    """Store ``records`` in ``folder/NAME.json`` (default ``docs/results``): a record replaces the stored
    one with the same ``keys`` values in its place (so a rerun row stays where it was), the others are
    kept, new keys go last; returns every stored record. A record whose measurements equal the stored
    one's (a table re-made from the same finished run) keeps the stored command, machine and note."""
    path = Path(folder if folder is not None else RESULTS_DIR) / f"{name}.json"
    stored = load_records(name, folder)
    fresh = {tuple(r[k] for k in keys): r for r in records}
    merged = []
    for old in stored:
        new = fresh.pop(tuple(old.get(k) for k in keys), old)
        merged.append(old if _measurements(new) == _measurements(old) else new)
    merged += list(fresh.values())
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(merged, indent=1) + "\n")
    os.replace(tmp, path)
    return merged
