"""What a training checkpoint holds (the model and the ``TrainState``), and how training resumes from it.

A checkpoint holds everything the next steps depend on: the model, the optimisers, the densification
statistics, every random state, the NaN guard's learning-rate scale, the settings and a fingerprint of
the training images. A run killed at any moment and started again with the same command therefore ends
with the parameters of an uninterrupted run (bitwise on a CPU), having lost at most one checkpoint
interval; a run folder trained with other settings or on other images is refused by name.
"""

from __future__ import annotations

import hashlib
import io
import json
from pathlib import Path

import torch

from ..config import OptimConfig, TrainConfig, config_to_dict
from ..data.dataset import ViewDataset
from ..run import RunError, changed_settings, gaussians_of, load_tensors, training_changes
from ..utils import atomic_write_bytes
from .state import TrainState
from .strategy import DefaultStrategy


def training_fingerprint(data: ViewDataset) -> str:
    """A sha256 of what training reads of a scene: every training image (at 8 bits, with its alpha), its
    camera and its time. The same scene in a moved folder has the same fingerprint; other images,
    cameras or times (another scene, another ``t_train_end``) have another."""
    digest = hashlib.sha256(f"{len(data)} views".encode())
    for view in data.views:
        cam = view.camera
        digest.update(json.dumps([view.time, cam.width, cam.height]).encode())
        for tensor in (cam.viewmat, cam.K):
            digest.update(tensor.detach().to("cpu", torch.float64).numpy().tobytes())
        for image in (view.image, view.alpha):
            digest.update((image.detach() * 255).round().to("cpu", torch.uint8).numpy().tobytes())
    return digest.hexdigest()


def check_resumable(ckpt: dict, cfg: TrainConfig, fingerprint: str, path: Path) -> list[str]:
    """The settings in which ``cfg`` differs from the checkpoint's that a finished run may take (those
    read after training); RunError naming ``path`` when the checkpoint was trained with other settings
    or on other images (checkpoints of earlier versions have no fingerprint: not compared)."""
    try:
        changed = changed_settings(ckpt.get("config", {}), cfg)
    except ValueError as err:
        raise RunError(f"{path}: {err}; train into a new --run folder") from err
    if training_changes(changed):
        raise RunError(
            f"{path}: the checkpoint was trained with other settings ({', '.join(changed)}); "
            "resume with the same settings, or train into a new --run folder"
        )
    saved = ckpt.get("data_fingerprint")
    if saved is not None and saved != fingerprint:
        trained_on = ckpt.get("config", {}).get("data", "?")
        raise RunError(
            f"{path}: the run was trained on other images ({trained_on}) than those of --data {cfg.data}; "
            f"resume with --data {trained_on}, or train into a new --run folder"
        )
    return changed


def checkpoint(
    state: TrainState, model, cfg: TrainConfig, fingerprint: str, t_max: float, device: torch.device
) -> dict:
    """Everything the next steps depend on: ``state`` (``TrainState.state_dict``) with ``model``, the
    settings and the images' fingerprint, as tensors and plain data (read back with
    ``torch.load(weights_only=True)``; ``run.py`` reads "model", "step", "train_seconds", "t_max" and
    "static_mask")."""
    saved = state.state_dict(device)
    return {
        "step": saved.pop("step"),
        "train_seconds": saved.pop("train_seconds"),
        "timings": saved.pop("timings"),
        "config": config_to_dict(cfg),
        "data_fingerprint": fingerprint,
        "t_max": t_max,
        "static_mask": model.static_mask,
        "model": model.state_dict(),
        **saved,
    }


def load_model(model, ckpt: dict) -> None:
    """Put ``model`` as the checkpoint ``ckpt`` ended (Gaussians, fields, per-camera colours)."""
    model.gaussians = gaussians_of(ckpt["model"])
    model.load_state_dict(ckpt["model"])


def restore(
    ckpt: dict, model, optim: OptimConfig, extent: float, strategy: DefaultStrategy, generator, device
) -> TrainState:
    """``model`` and the training state as ``checkpoint`` saved them (``TrainState.load_state_dict``)."""
    load_model(model, ckpt)
    model.set_static_mask(ckpt.get("static_mask"))
    state = TrainState.start(model, optim, extent, strategy, generator)
    state.load_state_dict(ckpt, device, model.static_mask)
    return state


def start_from(model, path: Path, device: torch.device) -> None:
    """Start ``model`` as the checkpoint ``path`` ended (its optimisers and statistics start afresh):
    a continual round goes on from the last one."""
    if not path.is_file():
        raise RunError(f"{path}: no checkpoint to start from (the previous round has not trained)")
    load_model(model, load_tensors(path, device))


class Checkpoints:
    """``RUN/checkpoint.pt``, written atomically, and the last good state in memory (the NaN guard goes
    back to it, and an interrupt in the middle of a step saves it)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.good: bytes | None = None

    def keep(self, state: dict) -> None:
        """Keep ``state`` in memory as the last good one."""
        buffer = io.BytesIO()
        torch.save(state, buffer)
        self.good = buffer.getvalue()

    def save(self, state: dict) -> Path:
        """Keep ``state`` as the last good one and write it."""
        self.keep(state)
        return self.write_good()

    def write_good(self) -> Path:
        return atomic_write_bytes(self.path, self.good)

    def last_good(self, device: torch.device) -> dict:
        return torch.load(io.BytesIO(self.good), map_location=device, weights_only=True)
