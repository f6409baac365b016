"""The C++ extensions: the build lock (a lock left by a killed build must not hang later runs), the
registry and `build_all`."""

import os
import re
import time

import pytest

from tracegs import cpp
from tracegs.cpp import EXTENSIONS, NativeExtension, build_all, wait_for_build_lock
from tracegs.machine import cpu_tag


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


def test_each_source_registers_its_operators_under_the_extensions_name():
    """`load()` returns torch.ops.<name>: the source's TORCH_LIBRARY must use that namespace."""
    for name, ext in EXTENSIONS.items():
        assert ext.name == name and ext.source.is_file(), ext.source
        assert re.findall(r"TORCH_LIBRARY\((\w+),", ext.source.read_text()) == [name]


def test_build_all_reports_an_extension_that_does_not_build(monkeypatch):
    def broken(openmp):
        raise RuntimeError("error: no such header")

    ext = NativeExtension(
        "tracegs_broken_cpu", EXTENSIONS["tracegs_ssim_cpu"].source, "broken kernel", "Python"
    )
    monkeypatch.setattr(ext, "build", broken)
    monkeypatch.setattr(cpp, "EXTENSIONS", {ext.name: ext})
    monkeypatch.setattr(cpp.shutil, "which", lambda _name: "/usr/bin/c++")
    (report,) = build_all(jobs=2)
    assert report["name"] == "tracegs_broken_cpu" and report["built"] is False
    assert "no such header" in report["error"] and ext.load() is None


def test_the_build_is_keyed_by_cpu_source_and_flags(tmp_path):
    """Two sources (two checkouts, two versions) build into two folders; the same source and flags
    into the same one; and a build for another CPU never shares one."""
    a, b = tmp_path / "a.cpp", tmp_path / "b.cpp"
    a.write_text("// one version\n")
    b.write_text("// one version\n")  # (the same text elsewhere: torch would rebuild on the path)
    one, other = (NativeExtension("tracegs_x_cpu", src, "x", "y") for src in (a, b))
    assert one.build_name(["-O3"], True) == NativeExtension("tracegs_x_cpu", a, "x", "y").build_name(
        ["-O3"], True
    )
    assert one.build_name(["-O3"], True) != other.build_name(["-O3"], True)
    assert one.build_name(["-O3"], True) != one.build_name(["-O2"], True)
    assert one.build_name(["-O3"], False).endswith("_serial")
    assert cpu_tag() in one.build_name(["-O3"], True)
