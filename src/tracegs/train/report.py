"""What a training run tells its user: the line printed when it starts, the progress bar (ETA, loss,
Gaussian count, stage) and the log lines of its steps, and the summary written when it ends."""

from __future__ import annotations

import json
import math

from .. import __version__
from ..config import TrainConfig
from ..data.dataset import ViewDataset
from ..machine import this_machine
from ..render.rendering import resolve_backend
from ..results import current_commit
from .state import TrainState


def stage(cfg: TrainConfig, step: int) -> str:
    """The stage of step ``step``, as the progress bar names it."""
    if cfg.method == "static" or step < cfg.static_iterations:
        return "stage 1 (static)"
    return f"stage 2 ({cfg.method})"


def report_step(
    cfg: TrainConfig, state: TrainState, total_steps: int, gaussians: int, stats: dict[str, float], bar, log
) -> None:
    """The progress bar's loss, ``gaussians`` (their count) and stage after a step; a log line every
    ``log_every`` steps and at the last one."""
    step = state.step
    bar.set_description(f"train {stage(cfg, step)}", refresh=False)
    bar.set_postfix(loss=f"{stats['loss']:.4f}", gaussians=gaussians, refresh=False)
    bar.update(1)
    if step % cfg.log_every == 0 or step == total_steps:
        seconds = round(state.train_seconds, 2)  # training time so far, resumed runs included
        log.write(json.dumps({"step": step, "gaussians": gaussians, "seconds": seconds, **stats}) + "\n")
        log.flush()


def describe(
    cfg: TrainConfig, data: ViewDataset, model, t_max: float, total_steps: int, views_per_step: int, device
) -> str:
    """What the run of ``cfg`` trains, in a line or two (printed when training starts)."""
    cam = data.views[0].camera
    frame = "world frame" if model.fields_see_world else "cameras' frame"
    text = (
        f"{cfg.method} ({cfg.preset}) on {len(data)} images of {cam.width}x{cam.height} px with "
        f"t <= {t_max:.3g}, {total_steps} steps ({views_per_step} view(s) a step in "
        f"stage 2) on {device} "
        f"({resolve_backend(cfg.backend, device)} rasteriser, fields in the {frame})"
    )
    if cfg.bf16 and not model.fields_bf16 and device.type == "cpu":
        text += (
            "\n  note: the fields train in fp32, not bf16: this CPU has no bf16 products (AMX or AVX512-BF16)"
        )
    pixels = cam.width * cam.height
    if device.type == "cpu" and cfg.preset == "cpu-fast" and pixels > 4 * 128 * 128:
        factor = math.ceil(math.sqrt(pixels / (128 * 128)))
        text += (
            f"\n  note: {cam.width}x{cam.height} is {pixels / (128 * 128):.0f}x the pixels of the 128 px "
            f"cpu-fast is made for, and the rasteriser's time grows with them; --downscale {factor} "
            "trains at about 128 px"
        )
    return text


def summary(
    cfg: TrainConfig, state: TrainState, model, t_max: float, extrapolation, device, threads=None
) -> dict:
    """What ``summary.json`` holds: the run's size, time, what the calibration chose (``extrapolation``,
    None before it), per-part timings, and what trained it (the tracegs version, its git commit when run
    from a checkout, the machine, the thread counts ``threads`` changed to)."""
    steps, chosen = max(state.step, 1), extrapolation
    return {
        "method": cfg.method,
        "preset": cfg.preset,
        "scene": str(cfg.data),
        "iterations": state.step,
        "gaussians": int(model.gaussians["means"].shape[0]),
        "train_seconds": round(state.train_seconds, 2),
        "t_max": t_max,
        "freeze_threshold": chosen.freeze_threshold if chosen else None,
        "freeze_psnr": chosen.report.get("freeze_psnr", {}) if chosen else {},
        "static_fraction": state.static_fraction,
        "free_bodies": chosen.report.get("free_bodies", []) if chosen else [],
        "joint_laws": chosen.report.get("joint_laws", []) if chosen else [],
        "nan_restorations": state.restorations,
        "ms_per_iteration": {k: round(1000 * v / steps, 2) for k, v in state.timings.items()},
        "device": str(device),
        "threads": threads.changes if threads else [],
        "rasteriser": resolve_backend(cfg.backend, device),
        "fields_dtype": "bf16" if model.fields_bf16 else "fp32",
        "tracegs": __version__,
        "commit": current_commit(),
        "machine": this_machine().record(),
    }
