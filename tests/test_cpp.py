"""The C++ extensions' build lock: a lock left by a killed build must not hang later runs."""

import os
import time

import pytest

from tracegs.cpp import wait_for_build_lock


def test_no_lock_returns_at_once(tmp_path):
    assert wait_for_build_lock(tmp_path) is False


def test_stale_lock_is_removed_with_a_warning(tmp_path):
    lock = tmp_path / "lock"
    lock.touch()
    old = time.time() - 3600
    os.utime(lock, (old, old))
    with pytest.warns(RuntimeWarning, match="stale build lock"):
        assert wait_for_build_lock(tmp_path, max_age=600) is True
    assert not lock.exists()


def test_held_lock_is_waited_for_then_taken_as_stale(tmp_path):
    lock = tmp_path / "lock"
    lock.touch()
    start = time.time()
    with pytest.warns(RuntimeWarning) as record:
        assert wait_for_build_lock(tmp_path, max_age=0.3, poll=0.05) is True
    messages = [str(w.message) for w in record]
    assert "waiting for the build lock" in messages[0] and "stale build lock" in messages[1]
    assert time.time() - start >= 0.25  # it waited for the lock to age, it did not remove it at once
    assert not lock.exists()
