"""The run folder: what ``tracegs train`` writes and every other command reads.

``RUN/config.json``        the resolved config (plain JSON parsed into the dataclasses of ``config/``)
``RUN/checkpoint.pt``      all that training goes on from (``train/checkpoint.py``; written atomically, a
                           killed run resumes from it to the parameters an uninterrupted run ends with)
``RUN/extrapolation.pt``   the post-training state (``extrapolate.ExtrapolationState``), chosen once on
                           the training images when training ends; ``tracegs calibrate`` chooses it again
``RUN/summary.json``       wall time, iterations, Gaussians, per-part timings, what the calibration chose
``RUN/log.jsonl``          losses and timings every ``log_every`` steps
``RUN/.lock``              held (``flock``) while a training writes the folder: "pid PID on HOST"

Both ``.pt`` files hold tensors and plain data only and are read with ``torch.load(weights_only=True)``:
opening someone else's run folder never executes code from it. Reading a run computes nothing.
"""

from __future__ import annotations

import contextlib
import json
import pickle
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import torch

from .config import TrainConfig, config_from_dict, config_to_dict
from .config.validate import check_choices
from .data.scene import load_scene
from .extrapolate import ExtrapolationState, Predictor, has_policy
from .machine import resolve_device, this_machine
from .models.gaussians import empty_like_params
from .models.trace import TraceModel
from .run_compat import migrate_config
from .utils import (
    LockHeld,
    atomic_torch_save,
    atomic_write_text,
    exclusive_lock,
    first_line,
)

CONFIG, CHECKPOINT, EXTRAPOLATION, SUMMARY, LOG, LOCK = (
    "config.json",
    "checkpoint.pt",
    "extrapolation.pt",
    "summary.json",
    "log.jsonl",
    ".lock",
)


class RunError(ValueError):
    """A run folder that cannot be read as it is; the message names the file and what to do."""


class TrainingDiverged(RunError):
    """Training went non-finite again after the last good state was restored with lower learning
    rates; the run folder keeps that state's checkpoint."""


@contextlib.contextmanager
def lock_run(run: Path) -> Iterator[None]:
    """Hold ``RUN/.lock`` while training writes the run folder; RunError when another training holds it.
    The lock of a killed process is released by the operating system, so a killed run resumes."""
    path = Path(run) / LOCK
    try:
        with exclusive_lock(path):
            yield
    except LockHeld as err:
        raise RunError(
            f"{run}: another training ({err.holder or 'another process'}) is writing this run folder "
            f"(it holds {path}); wait for it to end, or train into a new --run folder"
        ) from None


def truncate_log(path: Path, step: int) -> None:
    """Drop the lines of ``log.jsonl`` past ``step`` (and a half-written last line): those of steps that
    a killed or restored run trains again, so that each step is logged once."""
    path = Path(path)
    if not path.is_file():
        return
    kept = []
    for line in path.read_text().splitlines():
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(record, dict) and record.get("step", 0) <= step:
            kept.append(line + "\n")
    atomic_write_text(path, "".join(kept))


# ----- config -------------------------------------------------------------------------------------
def save_config(cfg: TrainConfig, path: Path) -> None:
    atomic_write_text(path, json.dumps(config_to_dict(cfg), indent=2))


def config_from_saved(data: dict, source: Path | str = "config") -> TrainConfig:
    """A config from its saved JSON data, that of an earlier version of tracegs included
    (``run_compat.migrate_config``); RunError naming ``source`` when it cannot be read."""
    try:
        cfg = config_from_dict(TrainConfig, migrate_config(data))
        check_choices(cfg)
        return cfg
    except (ValueError, TypeError) as err:
        raise RunError(f"{source}: {err}") from None


def run_data(cfg: TrainConfig, data: str | Path | None = None) -> Path:
    """The scene folder a run is evaluated on: ``data`` when given, else the one it was trained on;
    FileNotFoundError saying which when no training split of either layout is there."""
    path = Path(data or cfg.data)
    if not any((path / name).is_file() for name in ("transforms_train.json", "train_meta.json")):
        where = "" if data else f" (the run was trained with --data {cfg.data}, read from the current folder)"
        raise FileNotFoundError(f"{path}: no scene here: no transforms_train.json or train_meta.json{where}; "
                                "pass --data DIR")  # fmt: skip
    return path


def load_config(path: Path) -> TrainConfig:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no config.json here (is this a tracegs run folder?)")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as err:
        raise RunError(f"{path}: not valid JSON ({err})") from None
    return config_from_saved(data, path)


# ----- tensors ------------------------------------------------------------------------------------
def save_tensors(obj: dict, path: Path) -> Path:
    return atomic_torch_save(obj, path)


def load_tensors(path: Path, device: torch.device | str = "cpu") -> dict:
    """A ``.pt`` file of the run folder, read with ``weights_only=True``: tensors, numbers, strings and
    containers of them. Anything else (a pickled object, which could run code) is refused."""
    path = Path(path)
    if path.is_file() and path.stat().st_size == 0:
        raise RunError(f"{path}: empty file, not a checkpoint (a write was cut short?)")
    try:
        return torch.load(path, map_location=device, weights_only=True)
    except pickle.UnpicklingError as err:
        if not _written_by_torch_save(path):  # (other bytes, not an object refused)
            raise RunError(f"{path}: not a readable checkpoint (not a file torch.save writes)") from None
        detail = _unpickler_detail(err)
        raise RunError(
            f"{path}: refused: it holds pickled Python objects other than tensors and plain data, which "
            f"could run code when loaded ({detail}). tracegs never writes such objects; open run "
            "folders only from sources you trust."
        ) from None
    except (RuntimeError, EOFError, OSError) as err:
        raise RunError(f"{path}: not a readable checkpoint ({first_line(err).split('. ')[0]})") from None


def _written_by_torch_save(path: Path) -> bool:
    """Whether ``path`` starts as torch.save's files do: a zip archive, or (its legacy format) a pickle."""
    with open(path, "rb") as f:
        head = f.read(2)
    return zipfile.is_zipfile(path) or head[:1] == b"\x80"


def _unpickler_detail(err: pickle.UnpicklingError) -> str:
    """The global torch's restricted unpickler refused, as its message names it (else its first line)."""
    for line in str(err).splitlines():
        if "GLOBAL" in line:
            return line.split("error:", 1)[-1].strip().split(". ")[0].rstrip(".")
    return first_line(err)


CHECKPOINT_KEYS = ("model", "step", "train_seconds", "t_max")
MODEL_KEYS = ("aabb", "frame_interval")


def _check_checkpoint(ckpt, path: Path) -> dict:
    """``ckpt`` if it has what a trained run's checkpoint holds; RunError naming the missing key."""
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(ckpt, dict) or k not in ckpt]
    if not missing and isinstance(ckpt["model"], dict):
        missing = [f"model.{k}" for k in MODEL_KEYS if k not in ckpt["model"]]
    if missing:
        raise RunError(
            f"{path}: a checkpoint of another tracegs version, or not one of tracegs (no "
            f"{missing[0]!r}); train into a new --run folder"
        )
    return ckpt


def save_extrapolation(run: Path, state: ExtrapolationState) -> Path:
    return save_tensors(state.to_dict(), Path(run) / EXTRAPOLATION)


def load_extrapolation(run: Path, device: torch.device | str = "cpu") -> ExtrapolationState | None:
    """The saved post-training state, or None when the run has none (or one of another version)."""
    path = Path(run) / EXTRAPOLATION
    if not path.is_file():
        return None
    try:
        return ExtrapolationState.from_dict(load_tensors(path, device), device)
    except (ValueError, KeyError):
        return None


# ----- a trained run ------------------------------------------------------------------------------
@dataclass
class Run:
    """A trained run as read from its folder: its ``predictor`` (the model, its post-training state and
    settings: ``extrapolate.Predictor``) and what the folder says of it."""

    path: Path
    predictor: Predictor
    config: TrainConfig
    meta: dict
    """``step``, ``train_seconds``, ``t_max``."""

    @property
    def model(self) -> TraceModel:
        return self.predictor.model

    @property
    def state(self) -> ExtrapolationState:
        return self.predictor.state


def gaussians_of(model_state: dict):
    """Empty Gaussian parameters shaped as those of a checkpoint's ``model`` state dict (the number of
    Gaussians changes in training), for ``load_state_dict`` to fill."""
    return empty_like_params(
        {k.split(".", 1)[1]: v for k, v in model_state.items() if k.startswith("gaussians.")}
    )


def fields_in_bf16(cfg: TrainConfig) -> bool:
    """Whether a model of ``cfg`` runs its fields in bf16 on this machine: where the config asks for it
    and the CPU multiplies bf16 in hardware (``Machine.fast_bf16``, as `cpu-fast` chooses). A config
    made on another machine (a run loaded or resumed there, a sweep's task) asks for it where it would
    be emulated, ~8x slower a step; fp32 gives the fields' values exactly."""
    return cfg.bf16 and this_machine().fast_bf16


def _trained_model(cfg: TrainConfig, run: Path, device: str) -> tuple[TraceModel, dict]:
    """The model of ``run``'s checkpoint (in eval mode) and the checkpoint."""
    path = run / CHECKPOINT
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint (has `tracegs train --run {run}` finished a step?)")
    dev = resolve_device(device)
    ckpt = _check_checkpoint(load_tensors(path, dev), path)
    state = ckpt["model"]
    settings = cfg.model_config()
    model = TraceModel(settings, gaussians_of(state), state["aabb"], float(state["frame_interval"])).to(dev)
    try:
        model.load_state_dict(state)
    except (RuntimeError, KeyError, ValueError) as err:
        raise RunError(
            f"{path}: a checkpoint of another tracegs version, or of other settings than {run / CONFIG} "
            f"({first_line(err)}); train into a new --run folder"
        ) from None
    model.bf16 = fields_in_bf16(cfg)
    model.set_static_mask(ckpt.get("static_mask"))
    return model.eval(), ckpt


def load_run(run: str | Path, device: str = "auto", data: str | Path | None = None) -> Run:
    """A trained run (for rendering and evaluation), its predictor rendering on the background of its
    scene (``data`` when given, else the one it was trained on, when that folder is there). Nothing is
    fitted or trained here: a TRACE run without its post-training state raises RunError with the command
    that makes it."""
    run = Path(run)
    cfg = load_config(run / CONFIG)
    model, ckpt = _trained_model(cfg, run, device)
    dev = model.aabb.device
    state = load_extrapolation(run, dev)
    if state is None:
        from .run_compat import state_from_old_checkpoint

        state = state_from_old_checkpoint(ckpt, dev)
    if state is None:
        if has_policy(model):
            raise RunError(
                f"{run}: no post-training state ({EXTRAPOLATION}): training did not finish, or an older "
                f"tracegs wrote the run. Make it with `tracegs calibrate --run {run}` (it reads the "
                "training images; a finished run takes a minute)."
            )
        state = ExtrapolationState(t_max=float(ckpt["t_max"]))
    meta = {"step": ckpt["step"], "train_seconds": ckpt["train_seconds"], "t_max": ckpt["t_max"]}
    background = _scene_background(cfg, data)
    return Run(run, Predictor(model, state, cfg.extrapolation, background), cfg, meta)


def _scene_background(cfg: TrainConfig, data: str | Path | None) -> tuple | None:
    """The background of the run's scene (``data`` when given, else the one it was trained on), or
    None where there is no scene to read (a run folder copied without its scene renders on black)."""
    try:
        path = run_data(cfg, data)
    except FileNotFoundError:
        if data is not None:
            raise
        return None
    return load_scene(path, "train", cfg.downscale).background


def calibrate_run(
    run: str | Path, device: str = "auto", settings: dict | None = None, data: str | Path | None = None
) -> ExtrapolationState:
    """``tracegs calibrate``: choose a run's post-training state again on its training images (after
    changing ``extrapolation`` settings, or for a run written by an older tracegs) and save it.
    ``settings``: ``extrapolation`` fields by dotted name (``{"extrapolation.free_bodies": False}``),
    stored in the run's config; ``data``: the scene folder, when it has moved since training."""
    from .config import apply_overrides
    from .extrapolate import calibrate

    run = Path(run)
    cfg = load_config(run / CONFIG)
    if settings:
        if any(not k.startswith("extrapolation.") for k in settings):
            raise ValueError("tracegs calibrate changes extrapolation settings only (extrapolation.*)")
        cfg = apply_overrides(cfg, settings)
    if data is not None:
        cfg.data = Path(data).resolve()
    model, ckpt = _trained_model(cfg, run, device)
    predictor = calibrate(model, float(ckpt["t_max"]), cfg.extrapolation, run_data(cfg), cfg.downscale)
    save_extrapolation(run, predictor.state)
    save_config(cfg, run / CONFIG)
    summary = run / "summary.json"
    if summary.is_file():  # what the calibration chose, as the run's summary says it
        state = predictor.state
        chosen = {
            "freeze_threshold": state.freeze_threshold,
            "freeze_psnr": state.report.get("freeze_psnr", {}),
        }
        chosen |= {k: state.report.get(k, []) for k in ("free_bodies", "joint_laws")}
        atomic_write_text(summary, json.dumps(json.loads(summary.read_text()) | chosen, indent=2))
    return predictor.state


# ----- whether a run folder was made with a config ------------------------------------------------
RESUMABLE_CHANGES = frozenset(
    {"run", "data", "device", "threads", "backend", "bf16", "checkpoint_every", "log_every"}
)
"""Settings that may change when a killed run is resumed: where things are and the arithmetic of the
machine (bf16 where the CPU has AMX or AVX512-BF16), not what is trained."""


def is_after_training(name: str) -> bool:
    """Whether the dotted setting ``name`` is read only after the last step (``extrapolation.*``): a run
    resumed with new values of those keeps its training and is calibrated again."""
    return name.startswith("extrapolation.")


def training_changes(changed: list[str]) -> list[str]:
    """Of the ``changed`` settings, those that training reads (a finished run cannot keep them)."""
    return [name for name in changed if not is_after_training(name)]


def changed_settings(saved: dict, cfg: TrainConfig) -> list[str]:
    """Dotted names of the settings in which a run's saved config differs from ``cfg`` (the resumable
    ones excepted): empty when the run can go on, or be reused, with ``cfg``. Settings added since the
    run was saved read as their defaults; one this code no longer knows raises ValueError."""
    if saved:
        saved = config_to_dict(config_from_dict(TrainConfig, migrate_config(saved)))
    return _changed(saved, config_to_dict(cfg))


def _changed(saved: dict, current: dict, prefix: str = "") -> list[str]:
    changed = []
    for key in sorted(set(saved) | set(current)):
        name = prefix + key
        a, b = saved.get(key), current.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            changed += _changed(a, b, name + ".")
        elif a != b and name not in RESUMABLE_CHANGES:
            changed.append(name)
    return changed
