"""What this machine can do, decided once per process: the CPU (its model, the cores this process may
run on, its instruction-set flags), the instruction set ATen's kernels run (``isa``), whether it
multiplies bf16 in hardware (``fast_bf16``), torch's own thread count, the ``-march`` the C++
extensions are built for and the device ``auto`` picks. Every other module asks :func:`this_machine`;
a run records it once (``summary.json``'s ``machine``, :meth:`Machine.record`).

Standard library and torch only: the lowest layer of the package.
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import re
import subprocess
from dataclasses import dataclass
from pathlib import Path

import torch

TORCH_THREADS = torch.get_num_threads()
"""torch's own thread count (one per core it may use), read when the process first imports tracegs:
the most a training takes (``train/threads.py``), whatever a caller sets later."""

BF16_FLAGS = frozenset({"amx_bf16", "avx512_bf16"})
"""The CPU flags of bf16 dot products in hardware: AMX-BF16 tiles (Intel Xeon since Sapphire Rapids)
or AVX512-BF16 (AMD Zen 4 and later, Intel Cooper Lake)."""

FEATURES = (
    ("avx2", "AVX2"),
    ("avx512f", "AVX-512"),
    ("avx512_bf16", "AVX512-BF16"),
    ("amx_bf16", "AMX-BF16"),
)
"""The vector and matrix extensions a machine's description names: (CPU flag, name)."""

ISA_ENVIRONMENTS = {
    "native": {},
    "avx2": {
        "ATEN_CPU_CAPABILITY": "avx2",
        "DNNL_MAX_CPU_ISA": "AVX2",
        "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "TRACEGS_MARCH": "x86-64-v3",
    },
}
"""Environment variables that hold a process to an instruction set, for benchmarks (``--isa``): this
CPU's own, or an AVX2-only CPU's code paths (ATen's kernels, oneDNN, MKL and the extensions, built
for x86-64-v3) as an AVX2 laptop runs them. They act at start-up: set them for a new process."""


def json_of_process_held_to(isa: str, argv: list[str]):
    """Run ``argv`` (a Python benchmark) in a new process held to ``isa`` (``ISA_ENVIRONMENTS``) and
    return the JSON value it prints last; its earlier output is echoed. A failure raises
    RuntimeError with the end of its stderr."""
    child = subprocess.run(argv, env={**os.environ, **ISA_ENVIRONMENTS[isa]}, capture_output=True, text=True)
    if child.returncode != 0:
        raise RuntimeError(f"{' '.join(argv[:3])} (held to {isa}) failed:\n{child.stderr[-2000:]}")
    *earlier, last = child.stdout.strip().splitlines()
    if earlier:
        print("\n".join(earlier), flush=True)
    return json.loads(last)


@dataclass(frozen=True)
class Machine:
    """What this process runs on (:func:`this_machine`; :meth:`read` for another ``/proc/cpuinfo``)."""

    cpu: str
    """The CPU's model name, e.g. ``Intel Xeon Processor``."""
    cpus: frozenset[int]
    """The CPUs this process may run on (its affinity)."""
    threads: int
    """torch's own thread count (``TORCH_THREADS``)."""
    flags: frozenset[str]
    """The first CPU's instruction-set flags (empty where ``/proc/cpuinfo`` cannot be read)."""
    isa: str
    """The instruction set ATen's kernels run (``torch.backends.cpu.get_cpu_capability``: ``AVX512``,
    ``AVX2``, ...); below the CPU's own where ``ATEN_CPU_CAPABILITY`` holds it there."""
    fast_bf16: bool
    """Whether bf16 products are in hardware here (``BF16_FLAGS``, with ATen at AVX-512): there bf16
    autocast makes the fields' matrix products faster (AMX: oneDNN's tiles; AVX512-BF16: the fused
    MLPs' bf16 products, ``models/fused_mlp.py``); elsewhere bf16 is emulated and slower than fp32. A
    process held below AVX-512 (``ISA_ENVIRONMENTS``' avx2) runs as an AVX2-only CPU would: False."""
    march: str
    """The C++ extensions' ``-march``: ``TRACEGS_MARCH`` when set (e.g. ``x86-64-v3``, AVX2: a build
    for a cluster's older nodes, or to measure what an AVX2-only CPU gets), else ``native``."""
    device: str
    """The device ``auto`` picks: ``cuda`` where CUDA is available, else ``cpu``."""

    @classmethod
    def read(cls, cpuinfo: str | Path = "/proc/cpuinfo") -> Machine:
        """This process's machine, its CPU read from ``cpuinfo``."""
        model, flags = _cpuinfo(str(cpuinfo))
        model = re.sub(r"\((R|TM|tm)\)", "", model or platform.processor() or platform.machine())
        isa = torch.backends.cpu.get_cpu_capability()
        return cls(
            cpu=" ".join(model.split()) or "unknown CPU",
            cpus=frozenset(_affinity()),
            threads=TORCH_THREADS,
            flags=flags,
            isa=isa,
            fast_bf16=bool(flags & BF16_FLAGS) and isa.upper().startswith("AVX512"),
            march=os.environ.get("TRACEGS_MARCH", "native"),
            device="cuda" if torch.cuda.is_available() else "cpu",
        )

    @property
    def cores(self) -> int:
        """How many CPUs this process may run on."""
        return len(self.cpus)

    @property
    def features(self) -> list[str]:
        """The vector and matrix extensions of ``FEATURES`` the CPU has, e.g. ``["AVX2", "AVX-512"]``."""
        return [name for flag, name in FEATURES if flag in self.flags]

    @property
    def description(self) -> str:
        """This machine in one line: usable cores, CPU model and its vector / matrix extensions, e.g.
        ``2 cores, Intel Xeon Processor (AVX2, AVX-512, AMX-BF16)``; no GPU is named."""
        features = f" ({', '.join(self.features)})" if self.features else ""
        return f"{self.cores} core{'s' if self.cores != 1 else ''}, {self.cpu}{features}"

    def record(self) -> dict:
        """The machine as plain JSON data, as a run's ``summary.json`` records it."""
        return {
            "description": self.description,
            "cores": self.cores,
            "threads": self.threads,
            "isa": self.isa,
            "fast_bf16": self.fast_bf16,
            "march": self.march,
            "device": self.device,
        }


@functools.cache
def this_machine() -> Machine:
    """The machine of this process, read once."""
    return Machine.read()


def resolve_device(name: str = "auto") -> torch.device:
    """'auto' picks CUDA when present, else CPU (``Machine.device``); anything else is passed to
    ``torch.device``."""
    if name == "auto":
        return torch.device(this_machine().device)
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {name!r} requested but CUDA is not available")
    return device


@functools.cache
def cpu_tag() -> str:
    """Short hash of the CPU model and instruction-set flags (of every CPU ``/proc/cpuinfo`` lists):
    what the C++ extensions' builds are keyed by."""
    info = platform.machine() + platform.processor()
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()
        info += "".join(line for line in lines if line.startswith(("model name", "flags")))[:4096]
    except OSError:
        pass
    return hashlib.sha1(info.encode()).hexdigest()[:8]


def _cpuinfo(path: str) -> tuple[str, frozenset[str]]:
    """The first CPU's model name and flags in ``path`` (empty where it cannot be read)."""
    model, flags = "", None
    try:
        with open(path) as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and not model:
                    model = value.strip()
                elif key.strip() == "flags" and flags is None:
                    flags = frozenset(value.split())
                if model and flags is not None:
                    break
    except OSError:
        pass
    return model, flags or frozenset()


def _affinity() -> set[int]:
    try:
        return set(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not on Linux
        return set(range(os.cpu_count() or 1))
