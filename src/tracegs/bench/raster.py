"""Rasteriser speed benchmark: every available backend on the same random scenes
(``render/random_scene.py``), side by side.

``run_raster_bench()`` (CLI: ``tracegs bench raster [--isa native avx2] [--json FILE]``) times forward
and forward + backward of :func:`tracegs.render.rasterize` for each backend and workload, natively or
held to other instruction sets (``machine.ISA_ENVIRONMENTS``, each in a process of its own); with
``json_path`` it writes a results record (``tracegs.results``) there.
"""

from __future__ import annotations

import ctypes
import gc
import json
import math
import resource
import statistics
import sys
import threading
import time
from pathlib import Path

import torch

from ..machine import ISA_ENVIRONMENTS, json_of_process_held_to, resolve_device
from ..render.random_scene import random_scene
from ..render.rendering import available_backends, rasterize
from ..results import make_record, write_record
from ..utils import synchronize


def _rss_mb() -> float:
    """Current resident set size of this process (MB); Linux only, else the peak so far."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20
    except OSError:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        return peak / 2**20 if sys.platform == "darwin" else peak / 1024


def _release_free_memory() -> None:
    """Hand freed heap memory back to the OS (glibc), so that RSS measures live memory again."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class _PeakMemory:
    """Highest RSS above the starting RSS while the block runs, sampled every millisecond from a
    thread (the C++ kernels release the GIL, so the sampler sees their allocations too)."""

    def __enter__(self):
        _release_free_memory()
        self.base = self.peak = _rss_mb()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def _sample(self):
        while not self._stop.wait(0.001):
            self.peak = max(self.peak, _rss_mb())

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _rss_mb())
        self.mb = self.peak - self.base


class _PeakCudaMemory:
    """Peak CUDA memory allocated above the start while the block runs (PyTorch's allocator)."""

    def __init__(self, device: torch.device):
        self.device = device

    def __enter__(self):
        torch.cuda.synchronize(self.device)
        torch.cuda.reset_peak_memory_stats(self.device)
        self.base = torch.cuda.memory_allocated(self.device)
        return self

    def __exit__(self, *exc):
        torch.cuda.synchronize(self.device)
        self.mb = (torch.cuda.max_memory_allocated(self.device) - self.base) / 2**20


def _time_backend(scene: dict, backend: str, repeats: int, warmup: int) -> dict:
    params = ("means", "quats", "scales", "opacities", "colors")
    leaves = {k: scene[k].clone().requires_grad_(True) for k in params}
    rest = {k: v for k, v in scene.items() if k not in params}
    device = leaves["means"].device
    weights = torch.rand(scene["height"], scene["width"], 3, generator=torch.Generator().manual_seed(1))
    weights = weights.to(device)

    def fwd():
        with torch.no_grad():
            rasterize(**leaves, **rest, backend=backend)

    def fwd_bwd():
        out = rasterize(**leaves, **rest, backend=backend)
        loss = (out.image * weights).sum() + out.depth.mean()
        loss.backward()
        for v in leaves.values():
            v.grad = None

    timings = {}
    for name, fn in (("forward", fwd), ("forward_backward", fwd_bwd)):
        for _ in range(warmup):
            fn()
        samples = []
        for _ in range(repeats):
            synchronize(device)
            t0 = time.perf_counter()
            fn()
            synchronize(device)
            samples.append((time.perf_counter() - t0) * 1e3)
        timings[name] = statistics.median(samples)
    with _PeakCudaMemory(device) if device.type == "cuda" else _PeakMemory() as mem:  # one more, untimed
        fwd_bwd()
    return dict(
        ms_forward=timings["forward"],
        ms_forward_backward=timings["forward_backward"],
        peak_mb=mem.mb,
        repeats=repeats,
    )


def run_raster_bench(
    json_path: str | Path | None = None,
    widths: tuple[int, ...] = (128, 256),
    counts: tuple[int, ...] = (5000, 20000, 100000),
    repeats: int = 7,
    backends: list[str] | None = None,
    device: str = "cpu",
    isas: tuple[str, ...] = ("native",),
) -> list[dict]:
    """Time forward and forward + backward of every backend on every (width, count) workload.

    Median of ``repeats`` runs after one warm-up; the reference backend gets fewer repeats when it
    is slow (under ~10 s per workload). ``peak_mb`` is the peak resident memory that one forward +
    backward adds on top of what the process held before it (freed heap memory is returned to
    the OS first, glibc only; sampled every ms); on CUDA, the peak that PyTorch's allocator adds.
    ``device``: where the Gaussians live ('auto', 'cpu' or 'cuda'). ``isas``: instruction sets
    (``machine.ISA_ENVIRONMENTS``) other than ``("native",)`` run each in a child process, the native
    backend only beside this CPU's own (rows with an ``isa``). Returns one row per backend and
    workload.
    """
    if tuple(isas) != ("native",):
        unknown = set(isas) - set(ISA_ENVIRONMENTS)
        if unknown:
            raise ValueError(f"--isa: unknown {sorted(unknown)}; choose from {list(ISA_ENVIRONMENTS)}")
        if resolve_device(device).type != "cpu":
            raise ValueError("--isa measures the CPU backends: add --device cpu")
        records = []
        for isa in isas:
            args = dict(widths=widths, counts=counts, repeats=repeats, device=device)
            args["backends"] = backends if isa == "native" else ["native"]
            records += [{"isa": isa, **r} for r in _records_of_child(isa, args)]
        if json_path is not None:
            _write(records, json_path, resolve_device(device), isas)
        return records
    device = resolve_device(device)
    backends = list(backends) if backends is not None else available_backends(device)
    records = []
    for width in widths:
        height = width * 3 // 4
        for n in counts:
            scene = random_scene(n, width, height, seed=0)
            scene = {k: v.to(device) if torch.is_tensor(v) else v for k, v in scene.items()}
            for backend in backends:
                reps = repeats
                if backend == "reference":
                    t0 = time.perf_counter()
                    _time_backend(scene, backend, repeats=1, warmup=0)
                    once = time.perf_counter() - t0
                    reps = max(1, min(repeats, math.floor(10.0 / max(once, 1e-3))))
                rec = dict(backend=backend, device=device.type, width=width, height=height, gaussians=n)
                rec.update(
                    _time_backend(scene, backend, repeats=reps, warmup=1 if backend != "reference" else 0)
                )
                rec["threads"] = torch.get_num_threads()
                records.append(rec)
                print(
                    f"raster {backend:9s} {width}x{height} N={n:6d}: fwd {rec['ms_forward']:9.2f} ms, "
                    f"fwd+bwd {rec['ms_forward_backward']:9.2f} ms ({reps} reps)",
                    flush=True,
                )

    if json_path is not None:
        _write(records, json_path, device, isas)
    return records


def _records_of_child(isa: str, args: dict) -> list[dict]:
    """``run_raster_bench(**args)``'s rows from a new process held to ``isa`` (its variables act at
    start-up, and the extensions load once per process)."""
    code = (
        "import json, sys; from tracegs.bench.raster import run_raster_bench; "
        "print(json.dumps(run_raster_bench(**json.loads(sys.argv[1]))))"
    )
    return json_of_process_held_to(isa, [sys.executable, "-c", code, json.dumps(args)])


def _write(records: list[dict], json_path: str | Path, device: torch.device, isas: tuple[str, ...]) -> None:
    """The record: a row per backend and workload of the first instruction set, the others' times as
    columns beside them (``avx2_ms_forward``, ...)."""
    isas = tuple(isas)
    first = [r for r in records if r.get("isa", isas[0]) == isas[0]]
    rows = _with_speedups(first)
    extra = []
    for isa in isas[1:]:
        extra += [f"{isa}_ms_forward", f"{isa}_ms_forward_backward"]
        times = {(r["backend"], r["width"], r["gaussians"]): r for r in records if r.get("isa") == isa}
        for row in rows:
            other = times.get((row["backend"], row["width"], row["gaussians"]))
            if other is not None:
                row[f"{isa}_ms_forward"] = other["ms_forward"]
                row[f"{isa}_ms_forward_backward"] = other["ms_forward_backward"]
    isa_flag = "" if isas == ("native",) else f" --isa {' '.join(isas)}"
    command = f"tracegs bench raster --device {device.type}{isa_flag} --json {json_path}"
    title = f"Rasteriser forward / forward + backward ({device.type})"
    columns = ["backend", "image", "gaussians", "ms_forward", "ms_forward_backward", *extra, "peak_mb"]
    columns += ["speed-up fwd", "speed-up fwd+bwd", "threads"]
    notes = record_notes(isas)
    record = make_record(f"raster-{device.type}", rows, command, title=title, columns=columns, notes=notes)
    write_record(json_path, record)


def record_notes(isas: tuple[str, ...] = ("native",)) -> str:
    """The record's notes: how the rows are measured, and which instruction sets ``isas`` (each in a
    process of its own) give the rows (the first) and the columns beside them (the others)."""
    notes = (
        "Random scenes of render/random_scene.py, one camera, median of the repeats after a warm-up; "
        "peak_mb is the memory one forward + backward adds."
    )
    if tuple(isas) == ("native",):
        return notes
    held = {"native": "on this CPU's own code paths", "avx2": "held to an AVX2-only CPU's code paths"}
    how = [held.get(isa, f"held to {isa}") for isa in isas]
    notes += f" The rows run {how[0]}"
    notes += "".join(
        f"; the {isa} columns run the native rasteriser {h}" for isa, h in zip(isas[1:], how[1:], strict=True)
    )
    return notes + "."


def _with_speedups(records: list[dict]) -> list[dict]:
    """The rows with the image size and each backend's speed-up over the reference at its workload."""
    rows = []
    by_key = {(r["backend"], r["width"], r["gaussians"]): r for r in records}
    for r in records:
        row = dict(r)
        ref = by_key.get(("reference", r["width"], r["gaussians"]))
        if r["backend"] != "reference" and ref is not None:
            row["speed-up fwd"] = f"{ref['ms_forward'] / r['ms_forward']:.0f}x"
            row["speed-up fwd+bwd"] = f"{ref['ms_forward_backward'] / r['ms_forward_backward']:.0f}x"
        row["image"] = f"{r['width']}x{r['height']}"
        rows.append(row)
    return rows
