"""What a training run tells its user: the line printed when it starts, the progress bar (ETA, loss,
Gaussian count, stage) and the log lines of its steps, and the summary written when it ends."""

from __future__ import annotations

import json
import math

from .. import __version__
from ..machine import this_machine
from ..render.rendering import resolve_backend
from ..results import current_commit


def stage(trainer) -> str:
    """The stage of the next step, as the progress bar names it."""
    if trainer.cfg.method == "static" or trainer.step < trainer.cfg.static_iterations:
        return "stage 1 (static)"
    return f"stage 2 ({trainer.cfg.method})"


def report_step(trainer, stats: dict[str, float], bar, log) -> None:
    """The progress bar's loss, Gaussian count and stage; a log line every ``log_every`` steps."""
    n = trainer.model.gaussians["means"].shape[0]
    bar.set_description(f"train {stage(trainer)}", refresh=False)
    bar.set_postfix(loss=f"{stats['loss']:.4f}", gaussians=n, refresh=False)
    bar.update(1)
    if trainer.step % trainer.cfg.log_every == 0 or trainer.step == trainer.total_steps:
        seconds = round(trainer.train_seconds, 2)  # training time so far, resumed runs included
        log.write(json.dumps({"step": trainer.step, "gaussians": n, "seconds": seconds, **stats}) + "\n")
        log.flush()


def describe(trainer) -> str:
    """What this run trains, in a line or two (printed when training starts)."""
    cfg, cam = trainer.cfg, trainer.data.views[0].camera
    frame = "world frame" if trainer.model.fields_see_world else "cameras' frame"
    text = (
        f"{cfg.method} ({cfg.preset}) on {len(trainer.data)} images of {cam.width}x{cam.height} px with "
        f"t <= {trainer.t_max:.3g}, {trainer.total_steps} steps ({trainer.views_per_step} view(s) a step in "
        f"stage 2) on {trainer.device} "
        f"({resolve_backend(cfg.backend, trainer.device)} rasteriser, fields in the {frame})"
    )
    if cfg.bf16 and not trainer.model.fields_bf16 and trainer.device.type == "cpu":
        text += (
            "\n  note: the fields train in fp32, not bf16: this CPU has no bf16 products (AMX or AVX512-BF16)"
        )
    pixels = cam.width * cam.height
    if trainer.device.type == "cpu" and cfg.preset == "cpu-fast" and pixels > 4 * 128 * 128:
        factor = math.ceil(math.sqrt(pixels / (128 * 128)))
        text += (
            f"\n  note: {cam.width}x{cam.height} is {pixels / (128 * 128):.0f}x the pixels of the 128 px "
            f"cpu-fast is made for, and the rasteriser's time grows with them; --downscale {factor} "
            "trains at about 128 px"
        )
    return text


def summary(trainer) -> dict:
    """What ``summary.json`` holds: the run's size, time, what the calibration chose, per-part timings,
    and what trained it (the tracegs version, its git commit when run from a checkout, the machine)."""
    steps, state = max(trainer.step, 1), trainer.extrapolation
    return {
        "method": trainer.cfg.method,
        "preset": trainer.cfg.preset,
        "scene": str(trainer.cfg.data),
        "iterations": trainer.step,
        "gaussians": int(trainer.model.gaussians["means"].shape[0]),
        "train_seconds": round(trainer.train_seconds, 2),
        "t_max": trainer.t_max,
        "freeze_threshold": state.freeze_threshold if state else None,
        "freeze_psnr": state.report.get("freeze_psnr", {}) if state else {},
        "static_fraction": trainer.static_fraction,
        "free_bodies": state.report.get("free_bodies", []) if state else [],
        "joint_laws": state.report.get("joint_laws", []) if state else [],
        "nan_restorations": trainer.restorations,
        "ms_per_iteration": {k: round(1000 * v / steps, 2) for k, v in trainer.timings.items()},
        "device": str(trainer.device),
        "threads": trainer.threads.changes if trainer.threads else [],
        "rasteriser": resolve_backend(trainer.cfg.backend, trainer.device),
        "fields_dtype": "bf16" if trainer.model.fields_bf16 else "fp32",
        "tracegs": __version__,
        "commit": current_commit(),
        "machine": this_machine().record(),
    }
