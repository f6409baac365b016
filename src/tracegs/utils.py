"""Small shared helpers: atomic file writes, seeding and random states, file locks (what the machine
can do, the device included, is ``machine.py``'s)."""

from __future__ import annotations

import contextlib
import os
import random
import shutil
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch


def synchronize(device: torch.device) -> None:
    """Wait for the kernels queued on a CUDA ``device`` (a timer then measures their run, not their
    launch); nothing on CPU."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def seed_everything(seed: int) -> torch.Generator:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)
    return torch.Generator().manual_seed(seed)


def random_states(device: torch.device) -> dict:
    """Every global random state a training step draws from (Python's, NumPy's, torch's CPU one and, on
    CUDA, the device's), as tensors and plain data, for ``set_random_states`` to restore."""
    name, keys, pos, has_gauss, cached = np.random.get_state()
    states = {
        "python": random.getstate(),
        "numpy": {"keys": torch.from_numpy(keys.astype(np.int64)), "pos": int(pos)}
        | {"has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
        "torch": torch.get_rng_state(),
    }
    if device.type == "cuda":
        states["cuda"] = torch.cuda.get_rng_state(device)
    return states


def set_random_states(states: dict, device: torch.device) -> None:
    """Restore what ``random_states`` returned (states saved without NumPy's or CUDA's leave those as
    they are)."""
    random.setstate(states["python"])
    torch.set_rng_state(states["torch"].cpu())  # a checkpoint loaded onto CUDA moved it there
    if "numpy" in states:
        n = states["numpy"]
        keys = n["keys"].cpu().numpy().astype(np.uint32)
        np.random.set_state(("MT19937", keys, n["pos"], n["has_gauss"], n["cached_gaussian"]))
    if "cuda" in states and device.type == "cuda":
        torch.cuda.set_rng_state(states["cuda"].cpu(), device)


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()  # read once, at import: os.umask can only be read by setting it


def _atomic(path: Path, write) -> Path:
    """Write through a temporary file in the same folder, then rename: readers never see half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes the file private; outputs get the usual mode
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)
    return path


def atomic_write_text(path: Path, text: str) -> Path:
    return _atomic(path, lambda tmp: Path(tmp).write_text(text))


def atomic_write_bytes(path: Path, data: bytes) -> Path:
    return _atomic(path, lambda tmp: Path(tmp).write_bytes(data))


def atomic_torch_save(obj, path: Path) -> Path:
    return _atomic(path, lambda tmp: torch.save(obj, tmp))


def fresh_folder(out: Path, written_by: str, marker: str) -> Path:
    """An empty temporary folder beside ``out``, in which a command (``written_by``, e.g. "tracegs
    synth") writes what ``replace_folder`` then moves to ``out``; FileExistsError when ``out`` is a file,
    or a non-empty folder without ``marker`` (a path inside it: that command's own output)."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / marker).exists():
        raise FileExistsError(
            f"{out} is a non-empty folder that {written_by} did not write; not overwriting it"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    return tmp


def replace_folder(tmp: Path, out: Path) -> None:
    """Move the finished folder ``tmp`` to ``out``; an older output under that name is removed."""
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old)
    else:
        tmp.rename(out)


def remove_temporaries(path: Path) -> list[Path]:
    """Delete the temporary files that writes of ``path`` left behind when their process was killed
    (``.NAME.*.tmp`` beside it); returns them. Only for a writer that holds the folder's lock: another
    writer's file in flight would go too."""
    path = Path(path)
    stray = sorted(path.parent.glob(f".{path.name}.*.tmp"))
    for tmp in stray:
        tmp.unlink(missing_ok=True)
    return stray


class LockHeld(OSError):
    """The lock is held by another process; ``holder`` is what it wrote into the lock file."""

    def __init__(self, path: Path, holder: str):
        super().__init__(f"{path}: locked by {holder or 'another process'}")
        self.path, self.holder = path, holder


@contextlib.contextmanager
def exclusive_lock(path: Path) -> Iterator[None]:
    """Hold an exclusive lock on ``path`` (created, and holding "pid PID on HOST" while held) for the
    block; ``LockHeld`` when another process holds it. The lock is ``flock``'s: the operating system
    releases it when its process ends, however it ends, so the file of a killed process never blocks.
    Where ``fcntl`` does not exist (Windows) nothing is locked."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on Linux or macOS
        yield
        return
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            f.seek(0)
            raise LockHeld(path, f.read().strip()) from None
        f.seek(0)
        f.truncate()
        f.write(f"pid {os.getpid()} on {socket.gethostname()}\n")
        f.flush()
        try:
            yield
        finally:
            f.truncate(0)
            fcntl.flock(f, fcntl.LOCK_UN)


def atomic_write_image(path: Path, image: torch.Tensor | np.ndarray) -> Path:
    """Save a float [H, W, 3|4] image in [0, 1] as an 8-bit PNG."""
    import imageio.v3 as iio

    arr = image.detach().cpu().numpy() if isinstance(image, torch.Tensor) else np.asarray(image)
    arr = (np.clip(arr, 0, 1) * 255 + 0.5).astype(np.uint8)
    return _atomic(path, lambda tmp: iio.imwrite(tmp, arr, extension=Path(path).suffix or ".png"))


def first_line(err: BaseException) -> str:
    """The first line of an exception's message (its type's name when it has none), for one-line errors."""
    lines = str(err).strip().splitlines()
    return lines[0] if lines else type(err).__name__
