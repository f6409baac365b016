"""What a training checkpoint holds, and how a trainer is restored from it.

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
from collections import defaultdict
from pathlib import Path

import torch
from tqdm import tqdm

from ..config import TrainConfig, config_to_dict
from ..data.dataset import ViewDataset
from ..run import (
    CHECKPOINT,
    LOG,
    RunError,
    TrainingDiverged,
    changed_settings,
    gaussians_of,
    load_tensors,
    training_changes,
    truncate_log,
)
from ..utils import atomic_write_bytes, random_states, set_random_states
from .optim import colour_optimizer, gaussian_optimizers


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


def trainer_state(trainer) -> dict:
    """Everything the next steps of ``trainer`` depend on, as tensors and plain data (read back with
    ``torch.load(weights_only=True)``)."""
    model = trainer.model
    return {
        "step": trainer.step,
        "train_seconds": trainer.train_seconds,
        "timings": dict(trainer.timings),
        "config": config_to_dict(trainer.cfg),
        "data_fingerprint": trainer.fingerprint,
        "t_max": trainer.t_max,
        "static_mask": model.static_mask,
        "model": model.state_dict(),
        "optimizers": {k: o.state_dict() for k, o in trainer.optimizers.items()},
        "field_optimizer": trainer.field_opt.state_dict() if trainer.field_opt is not None else None,
        "colour_optimizer": trainer.colour_opt.state_dict() if trainer.colour_opt is not None else None,
        "strategy": dict(trainer.strategy_state),
        "lr_scale": trainer.lr_scale,
        "restorations": list(trainer.restorations),
        "rng": random_states(trainer.device) | {"generator": trainer.generator.get_state()},
    }


def restore_trainer_state(trainer, ckpt: dict) -> None:
    """Put ``trainer`` in the state ``trainer_state`` saved; parts that checkpoints of earlier versions
    lack (densification statistics, NumPy's random state, the learning-rate scale) start afresh."""
    model = trainer.model
    model.gaussians = gaussians_of(ckpt["model"])
    model.load_state_dict(ckpt["model"])
    trainer.optimizers = gaussian_optimizers(model.gaussians, trainer.cfg.optim, trainer.extent)
    for k, o in trainer.optimizers.items():
        o.load_state_dict(ckpt["optimizers"][k])
    if trainer.field_opt is not None and ckpt["field_optimizer"] is not None:
        trainer.field_opt.load_state_dict(ckpt["field_optimizer"])
    if trainer.colour_opt is not None:  # (made again: loading the model may resize the colours)
        trainer.colour_opt = colour_optimizer(model.camera_colour, trainer.cfg.optim)
        if ckpt.get("colour_optimizer") is not None:
            trainer.colour_opt.load_state_dict(ckpt["colour_optimizer"])
    trainer.strategy_state = trainer.strategy.initialize_state() | ckpt.get("strategy", {})
    trainer.step, trainer.train_seconds = ckpt["step"], ckpt["train_seconds"]
    trainer.lr_scale = float(ckpt.get("lr_scale", 1.0))
    trainer.restorations = list(ckpt.get("restorations", []))
    model.set_static_mask(ckpt.get("static_mask"))
    mask = model.static_mask
    trainer.static_fraction = None if mask is None else float(mask.float().mean())
    trainer.timings = defaultdict(float, ckpt.get("timings", {}))
    set_random_states(ckpt["rng"], trainer.device)
    if "generator" in ckpt["rng"]:
        trainer.generator.set_state(ckpt["rng"]["generator"].cpu())


def start_from(trainer, path: Path) -> None:
    """Start ``trainer``'s model as the checkpoint ``path`` ended (Gaussians, fields, per-camera
    colours), with fresh optimisers and statistics: a continual round goes on from the last one."""
    if not path.is_file():
        raise RunError(f"{path}: no checkpoint to start from (the previous round has not trained)")
    ckpt = load_tensors(path, trainer.device)
    model = trainer.model
    model.gaussians = gaussians_of(ckpt["model"])
    model.load_state_dict(ckpt["model"])
    trainer.optimizers = gaussian_optimizers(model.gaussians, trainer.cfg.optim, trainer.extent)
    trainer.colour_opt = colour_optimizer(model.camera_colour, trainer.cfg.optim)
    trainer.strategy_state = trainer.strategy.initialize_state()


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


def restore_after(trainer, err) -> None:
    """The NaN guard after ``err`` (``guard.NonFinite``): back to the last good state with the learning
    rates times ``optim.nan_lr_factor``; the second time, that state is saved and ``TrainingDiverged``
    raised."""
    factor = trainer.cfg.optim.nan_lr_factor
    lr_scale, restorations, seconds = trainer.lr_scale, trainer.restorations, trainer.train_seconds
    restore_trainer_state(trainer, trainer.checkpoints.last_good(trainer.device))
    trainer.train_seconds = seconds  # the time spent is spent
    truncate_log(trainer.run / LOG, trainer.step)
    if restorations:
        trainer.save()
        first = restorations[0]
        raise TrainingDiverged(
            f"{trainer.run}: training diverged: {err} after the {first['what']} at step {first['step']} "
            f"had restored step {first['to_step']} with the learning rates x{factor}; "
            f"{trainer.run / CHECKPOINT} keeps step {trainer.step}, the last good state"
        )
    trainer.lr_scale = lr_scale * factor
    trainer.restorations = [*restorations, {"step": err.step, "to_step": trainer.step, "what": err.what}]
    if trainer.progress:
        tqdm.write(f"{err}: restored step {trainer.step}, learning rates x{factor}")
