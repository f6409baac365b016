"""How many threads a training uses, chosen from what the machine's other work leaves free.

PyTorch's CPU threads meet at a barrier after every parallel op, and a training step is hundreds of
small ops. When another process holds one of the cores, the thread that shares that core runs only
in the scheduler's time slices, and every barrier waits for it: a step then costs ~40x its time
(measured: 2 s instead of 0.05 s on 2 cores). Fewer threads than free cores lose only the parallel
share of the arithmetic. So a training counts the cores other processes keep busy, when it starts
and every ``RECHECK_SECONDS`` after, and uses the free ones (at least one, at most torch's default).
A thread count set by the user (``--threads N``, or ``OMP_NUM_THREADS`` in the environment) is kept.
Only the CPUs this process may run on (its affinity) are counted.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import torch

from ..machine import this_machine

RECHECK_SECONDS = 30.0
"""How often a training counts the busy cores again (the check itself reads two small /proc files)."""
SAMPLE_SECONDS = 0.2
"""How long the first count watches the cores."""


def cpu_jiffies(cpus: set[int], stat: str | None = None) -> tuple[int, int]:
    """(busy, total) clock ticks so far of the CPUs ``cpus``, from /proc/stat (or its text ``stat``);
    idle and iowait are not busy."""
    if stat is None:
        with open("/proc/stat") as f:
            stat = f.read()
    busy = total = 0
    for line in stat.splitlines():
        name, *values = line.split()
        if not name.startswith("cpu") or name == "cpu" or int(name[3:]) not in cpus:
            continue
        ticks = [int(v) for v in values[:8]]  # user nice system idle iowait irq softirq steal
        total += sum(ticks)
        busy += sum(ticks) - ticks[3] - ticks[4]
    return busy, total


def own_ticks() -> float:
    """Clock ticks of CPU time this process has used (all its threads), and the children it waited for
    (the compiler that builds the C++ extensions on first use is ours too)."""
    t = os.times()
    return (t.user + t.system + t.children_user + t.children_system) * os.sysconf("SC_CLK_TCK")


def busy_cores(before: tuple[int, int, float], after: tuple[int, int, float], cpus: int) -> float:
    """Cores that other processes kept busy between two ``(busy, total, own)`` tick counts of ``cpus`` CPUs."""
    total = after[1] - before[1]
    if total <= 0:
        return 0.0
    others = (after[0] - before[0]) - (after[2] - before[2])
    return max(0.0, others / (total / cpus))


def free_threads(busy: float, cpus: int, most: int) -> int:
    """Threads to use when other processes keep ``busy`` of ``cpus`` cores busy: the free cores (a core
    counts as taken from half of it busy), at least 1, at most ``most``."""
    return max(1, min(most, cpus - int(busy + 0.5)))


@dataclass
class ThreadPolicy:
    """``threads`` > 0: that many threads throughout; 0: the free cores, counted at ``start`` and again
    at ``check`` every ``RECHECK_SECONDS``; with ``OMP_NUM_THREADS`` set, torch's count throughout."""

    threads: int = 0
    most: int = field(default_factory=lambda: this_machine().threads)
    """The most threads it takes (default: torch's own count, one per core it may use)."""
    cpus: set[int] = field(default_factory=lambda: set(this_machine().cpus))
    """The CPUs whose busy cores it counts (default: those this process may run on)."""
    changes: list[dict] = field(default_factory=list)
    """Every change: {"seconds", "busy", "threads"} (the run summary reports them)."""
    _last: tuple[int, int, float] | None = None
    _last_time: float = 0.0
    _t0: float = field(default_factory=time.perf_counter)
    _before: int = 0

    def __enter__(self) -> ThreadPolicy:
        self._before = torch.get_num_threads()
        self.start()
        return self

    def __exit__(self, *exc) -> None:  # the process keeps the thread count it had
        torch.set_num_threads(self._before)

    @property
    def adaptive(self) -> bool:
        return self.threads <= 0 and "OMP_NUM_THREADS" not in os.environ and os.path.exists("/proc/stat")

    def _sample(self) -> tuple[int, int, float]:
        return (*cpu_jiffies(self.cpus), own_ticks())

    def start(self) -> int:
        """Set the thread count for the start of training; returns it."""
        if self.threads > 0:
            torch.set_num_threads(self.threads)
        elif self.adaptive:
            before = self._sample()
            time.sleep(SAMPLE_SECONDS)
            self._set(before, self._sample())
        return torch.get_num_threads()

    def check(self) -> int:
        """Between steps: count the busy cores over the time since the last count (every
        ``RECHECK_SECONDS``) and set the thread count anew; returns it."""
        now = time.perf_counter()
        if self._last is not None and now - self._last_time >= RECHECK_SECONDS:  # (set when adaptive)
            self._set(self._last, self._sample())
        return torch.get_num_threads()

    def _set(self, before: tuple[int, int, float], now: tuple[int, int, float]) -> None:
        """Set the thread count from the busy cores between the samples ``before`` and ``now``."""
        busy = busy_cores(before, now, len(self.cpus))
        self._last, self._last_time = now, time.perf_counter()
        n = free_threads(busy, len(self.cpus), self.most)
        if n != torch.get_num_threads() or not self.changes:
            torch.set_num_threads(n)
            seconds = round(self._last_time - self._t0, 1)
            self.changes.append({"seconds": seconds, "busy": round(busy, 2), "threads": n})
