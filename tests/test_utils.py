"""Atomic writes: a reader sees the old file or the new one, and the new one has the usual mode."""

import os
import stat

import pytest

from tracegs.utils import atomic_write_text


def test_atomic_write_replaces_the_file_with_the_umask_mode_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "out" / "summary.json"
    atomic_write_text(path, "old")
    atomic_write_text(path, "new")
    assert path.read_text() == "new"
    assert os.listdir(path.parent) == ["summary.json"]
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask  # not mkstemp's private 0o600


def test_a_failed_write_keeps_the_previous_file(tmp_path):
    from tracegs.utils import _atomic

    path = tmp_path / "checkpoint.pt"
    atomic_write_text(path, "good")

    def fail(tmp):
        open(tmp, "w").write("half")
        raise OSError("disk full")

    with pytest.raises(OSError, match="disk full"):
        _atomic(path, fail)
    assert path.read_text() == "good" and os.listdir(tmp_path) == ["checkpoint.pt"]


def test_remove_temporaries_deletes_the_files_a_killed_write_left(tmp_path):
    from tracegs.utils import remove_temporaries

    path = tmp_path / "checkpoint.pt"
    path.write_text("good")
    stray = [tmp_path / ".checkpoint.pt.abc123.tmp", tmp_path / ".checkpoint.pt.x.tmp"]
    for tmp in stray:
        tmp.write_text("half")
    (tmp_path / ".config.json.y.tmp").write_text("another file's")
    assert remove_temporaries(path) == sorted(stray)
    assert sorted(os.listdir(tmp_path)) == [".config.json.y.tmp", "checkpoint.pt"]


def test_an_exclusive_lock_refuses_a_second_holder_and_is_released(tmp_path):
    import socket

    from tracegs.utils import LockHeld, exclusive_lock

    path = tmp_path / ".lock"
    with exclusive_lock(path):
        assert path.read_text() == f"pid {os.getpid()} on {socket.gethostname()}\n"
        with pytest.raises(LockHeld) as err, exclusive_lock(path):  # another open file: refused
            pass
        assert err.value.holder == f"pid {os.getpid()} on {socket.gethostname()}"
    with exclusive_lock(path):  # released at the end of the block
        pass


def test_random_states_round_trip_every_generator():
    import random

    import numpy as np
    import torch

    from tracegs.utils import random_states, set_random_states

    states = random_states(torch.device("cpu"))
    first = (random.random(), float(np.random.rand()), np.random.randn(), float(torch.rand(())))
    random.random(), np.random.rand(3), torch.rand(5)  # move each generator on
    set_random_states(states, torch.device("cpu"))
    assert (random.random(), float(np.random.rand()), np.random.randn(), float(torch.rand(()))) == first
