"""C++/OpenMP extensions (the CPU rasteriser, SSIM, RK2, the HexPlane grid's kernels, the fields' MLPs), built by
``build_all`` (``tracegs build``, which ``scripts/install.sh`` runs) or on first use.

Each extension is one ``.cpp`` file, JIT-compiled with ``torch.utils.cpp_extension.load`` and
cached in torch's extensions folder (``TORCH_EXTENSIONS_DIR``, default ``~/.cache/torch_extensions``).
Its functions are operators registered by ``TORCH_LIBRARY(<name>, m)`` in the source, under the
extension's ``name``; ``load()`` returns ``torch.ops.<name>``.
It needs a C++20 compiler; OpenMP (g++ ``-fopenmp``, clang with libomp) makes it multi-threaded.
If it cannot be built, :meth:`NativeExtension.load` returns ``None`` and warns once, and the caller
falls back to its pure-PyTorch path.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import time
import warnings
from pathlib import Path

from .machine import cpu_tag, this_machine


def compiler() -> str:
    return os.environ.get("CXX", "c++")


def supports_flag(flag: str) -> bool:
    """Whether the C++ compiler accepts ``flag`` (e.g. -march=native is missing on some toolchains)."""
    try:
        res = subprocess.run(
            [compiler(), flag, "-x", "c++", "-E", "-o", os.devnull, "-"],
            input=b"",
            capture_output=True,
            timeout=60,
        )
        return res.returncode == 0
    except (OSError, subprocess.SubprocessError):
        return False


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[-1] if text else type(err).__name__


STALE_LOCK_SECONDS = 600.0
"""A build lock older than this is taken as left behind by a killed process (a build takes 1-2 min)."""


def wait_for_build_lock(build_dir: Path, max_age: float = STALE_LOCK_SECONDS, poll: float = 1.0) -> bool:
    """Wait while another process holds ``build_dir/lock``; remove it once it is older than ``max_age``
    seconds. Returns True if a stale lock was removed.

    torch's JIT loader holds that lock while it (re)builds, and a later load waits for it without a
    time limit: a process killed in that window (Ctrl-C during the first build, a killed run) would
    otherwise leave every later run hanging silently.
    """
    lock = Path(build_dir) / "lock"
    told = False
    while True:
        try:
            age = time.time() - lock.stat().st_mtime
        except OSError:  # no lock (or it just went away)
            return False
        if age >= max_age:
            lock.unlink(missing_ok=True)
            warnings.warn(
                f"tracegs: removed the stale build lock {lock} ({age / 60:.0f} min old, left by a killed build)",
                RuntimeWarning,
                stacklevel=2,
            )
            return True
        if not told:
            warnings.warn(
                f"tracegs: waiting for the build lock {lock} (another process is building the extension; "
                f"if none is, delete that file; it is taken as stale after {max_age / 60:.0f} min)",
                RuntimeWarning,
                stacklevel=2,
            )
            told = True
        time.sleep(poll)


def _build_directory(name: str) -> Path | None:
    """Where torch builds the extension ``name`` (None if this torch does not say)."""
    try:
        from torch.utils.cpp_extension import _get_build_directory

        return Path(_get_build_directory(name, verbose=False))
    except (ImportError, TypeError):
        return None


class NativeExtension:
    """One JIT-built C++ extension: ``load()`` builds it once, then returns the module (or ``None``).

    ``what`` names it in warnings ("native CPU rasteriser"), ``fallback`` says what runs instead.
    """

    def __init__(self, name: str, source: Path, what: str, fallback: str, cflags: tuple[str, ...] = ()):
        self.name, self.source, self.what, self.fallback = name, Path(source), what, fallback
        self.cflags = list(cflags)  # after the common flags (a later flag overrides an earlier one)
        self.module = None
        self.error: str | None = None

    def build(self, openmp: bool):
        from torch.utils.cpp_extension import load

        _ninja_on_path()
        cflags = ["-O3", "-ffp-contract=off"]
        # Same float results in forward and backward loops (the rasteriser decides alpha thresholds in
        # both independently) need identical rounding: no FMA contraction, no fast-math.
        march = this_machine().march
        if supports_flag(f"-march={march}"):
            cflags.append(f"-march={march}")
        cflags += self.cflags
        ldflags = []
        if openmp:
            cflags.append("-fopenmp")
            ldflags.append("-fopenmp")
        name = self.build_name(cflags + ldflags, openmp)
        build_dir = _build_directory(name)
        if build_dir is not None:
            wait_for_build_lock(build_dir)
        load(
            name=name,
            sources=[str(self.source)],
            extra_cflags=cflags,
            extra_ldflags=ldflags,
            is_python_module=False,
        )
        import torch

        return getattr(torch.ops, self.name)  # the source's TORCH_LIBRARY(<name>, m) registered these

    def build_name(self, flags: list[str], openmp: bool) -> str:
        """The build's folder name in torch's cache: the extension's name, the CPU, and the source (its
        path and text) and flags. -march=native binaries are CPU specific: keyed by CPU, a home
        directory shared between different machines never loads one built for another (SIGILL, no
        fallback possible). Keyed by source, two checkouts (a user's install beside a clone, a
        benchmark of an older commit) each keep their build instead of rebuilding the other's on every
        switch: torch keeps one build per name and rebuilds when the source's path or text differs."""
        march = this_machine().march
        tag = cpu_tag() if march == "native" else f"{cpu_tag()}_{march.replace('-', '_').replace('.', '_')}"
        key = [str(self.source.resolve()), self.source.read_text(), *flags]
        content = hashlib.sha1("\0".join(key).encode()).hexdigest()[:8]
        return f"{self.name}_{tag}_{content}" + ("" if openmp else "_serial")

    def load(self):
        """Build (first call) or return the module; ``None`` (with one warning) if that fails."""
        if self.module is not None or self.error is not None:
            return self.module
        if shutil.which(compiler()) is None:
            self.error = f"no C++ compiler found ({compiler()!r} is not on PATH; set CXX)"
        else:
            try:
                self.module = self.build(openmp=True)
            except Exception as err_omp:  # noqa: BLE001 - any build failure means "fall back"
                try:
                    self.module = self.build(openmp=False)
                    warnings.warn(
                        f"tracegs: built the {self.what} without OpenMP (single-threaded); "
                        f"the OpenMP build failed: {_first_line(err_omp)}",
                        RuntimeWarning,
                        stacklevel=3,
                    )
                except Exception as err:  # noqa: BLE001
                    self.error = f"building the C++ extension failed: {_first_line(err)}"
        if self.error is not None:
            warnings.warn(
                f"tracegs: {self.what} unavailable, {self.error}; falling back to {self.fallback}.",
                RuntimeWarning,
                stacklevel=3,
            )
        return self.module


def _ninja_on_path() -> None:
    """torch builds extensions with the ``ninja`` binary, which the ninja package installs into the
    venv's ``bin/``: not on PATH when the venv is not activated (``.venv/bin/tracegs``)."""
    try:
        import ninja
    except ImportError:
        return
    bin_dir = str(getattr(ninja, "BIN_DIR", ""))
    path = os.environ.get("PATH", "")
    if bin_dir and bin_dir not in path.split(os.pathsep):
        os.environ["PATH"] = bin_dir + os.pathsep + path


_PACKAGE = Path(__file__).resolve().parent
EXTENSIONS: dict[str, NativeExtension] = {
    name: NativeExtension(name, _PACKAGE / source, what, fallback, *flags)
    for name, source, what, fallback, *flags in (
        ("tracegs_raster_cpu", "render/csrc/raster_cpu.cpp", "native CPU rasteriser",
         "the (much slower) pure-PyTorch reference backend"),
        ("tracegs_ssim_cpu", "render/csrc/ssim_cpu.cpp", "native CPU SSIM", "pytorch-msssim's SSIM"),
        ("tracegs_rk2_cpu", "physics/csrc/rk2_cpu.cpp", "native RK2 integrator", "the PyTorch sub-steps"),
        ("tracegs_hexplane_cpu", "models/csrc/hexplane_cpu.cpp", "native HexPlane kernels", "torch's grid_sample"),
        # (products, not a forward and a backward that must round alike: fused multiply-adds allowed)
        ("tracegs_mlp_cpu", "models/csrc/mlp_cpu.cpp", "fused field MLPs", "their PyTorch layers",
         ("-ffp-contract=fast",)),
    )
}  # fmt: skip
"""The package's extensions by name; each module that uses one takes it from here."""


def build_all(jobs: int | None = None) -> list[dict]:
    """Build (or load from the cache) every extension of ``EXTENSIONS`` now, ``jobs`` at a time
    (default: one per CPU), instead of each on its first use; what ``tracegs build`` and
    ``scripts/install.sh`` run. Returns one dict per extension: ``name``, ``what``, ``built``,
    ``seconds`` and ``error`` (why it fell back, else None).

    Each build is a compiler process (torch runs ninja), so threads build them side by side."""
    from concurrent.futures import ThreadPoolExecutor

    def one(ext: NativeExtension) -> dict:
        start = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # the error is in the report
            module = ext.load()
        seconds = round(time.perf_counter() - start, 2)
        return {
            "name": ext.name,
            "what": ext.what,
            "built": module is not None,
            "seconds": seconds,
            "error": ext.error,
        }

    workers = max(1, jobs or os.cpu_count() or 1)
    with ThreadPoolExecutor(max_workers=min(workers, len(EXTENSIONS))) as pool:
        return list(pool.map(one, EXTENSIONS.values()))


def format_build_report(report: list[dict]) -> str:
    """``build_all``'s report as ``tracegs build`` prints it: a line an extension, ready or its fallback."""
    return "\n".join(
        f"{e['what']}: "
        + (f"ready ({e['seconds']:.0f} s)" if e["built"] else f"not built ({e['error']}); its fallback runs")
        for e in report
    )
