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
