"""The thread count of a training, chosen from the cores other processes leave free (train/threads.py)."""

import os
import subprocess
import sys

import pytest
import torch

from tracegs.train import threads
from tracegs.train.threads import ThreadPolicy, busy_cores, cpu_jiffies, free_threads

STAT = """cpu  300 0 100 500 0 0 0 0 0 0
cpu0 100 0 50 250 0 0 0 0 0 0
cpu1 200 0 50 250 10 0 0 0 0 0
intr 12345
"""


def test_proc_stat_counts_the_busy_ticks_of_the_cpus_asked_for():
    assert cpu_jiffies({0}, STAT) == (150, 400)
    assert cpu_jiffies({1}, STAT) == (250, 510)  # iowait is idle
    assert cpu_jiffies({0, 1}, STAT) == (400, 910)
    assert cpu_jiffies({5}, STAT) == (0, 0)


def test_busy_cores_leave_out_this_process_own_time():
    # 2 CPUs over 100 ticks each (200 in all): 150 busy, of which 50 ours -> 1 core of others
    assert busy_cores((0, 0, 0.0), (150, 200, 50.0), cpus=2) == pytest.approx(1.0)
    assert busy_cores((0, 0, 0.0), (100, 200, 100.0), cpus=2) == pytest.approx(0.0)
    assert busy_cores((5, 5, 0.0), (5, 5, 0.0), cpus=2) == 0.0  # no time passed


@pytest.mark.parametrize(
    ("busy", "cpus", "most", "expected"),
    [
        (0.0, 2, 2, 2),
        (0.4, 2, 2, 2),
        (0.6, 2, 2, 1),
        (1.0, 2, 2, 1),
        (2.0, 2, 2, 1),
        (1.0, 8, 4, 4),
        (5.2, 8, 8, 3),
    ],
)
def test_free_threads_are_the_free_cores(busy, cpus, most, expected):
    assert free_threads(busy, cpus, most) == expected


def test_a_thread_count_given_is_kept_and_the_old_one_restored_after():
    before = torch.get_num_threads()
    with ThreadPolicy(threads=1) as policy:
        assert torch.get_num_threads() == 1
        assert policy.check() == 1
    assert torch.get_num_threads() == before


def test_omp_num_threads_turns_the_counting_off(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert not ThreadPolicy().adaptive


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2 or not os.path.exists("/proc/stat"), reason="2+ CPUs")
def test_a_training_beside_busy_cores_takes_the_free_one(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    cpus = sorted(os.sched_getaffinity(0))
    hogs = [
        subprocess.Popen(
            [sys.executable, "-c", "while True: pass"], preexec_fn=lambda c=c: os.sched_setaffinity(0, {c})
        )
        for c in cpus[1:]
    ]
    try:
        with ThreadPolicy(most=len(cpus)) as policy:
            assert torch.get_num_threads() == 1  # every CPU but one is busy
            assert policy.changes[0]["busy"] >= len(hogs) - 0.5
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
    monkeypatch.setattr(threads, "RECHECK_SECONDS", 0.0)
    with ThreadPolicy(most=len(cpus)) as policy:  # counted again when they are gone
        assert policy.check() >= 1


def test_the_work_of_children_this_process_waited_for_is_its_own():
    before = threads.own_ticks()
    subprocess.run([sys.executable, "-c", "x = sum(i * i for i in range(3_000_000))"], check=True)
    assert threads.own_ticks() - before >= 1  # at least a tick of the child's CPU time
