"""The training loop: stage 1 (static 3DGS at t = 0), stage 2 (TRACE or DefGS), checkpoints, resume,
and the post-training calibration of the extrapolation state when the last step is done.

What the run folder holds, and how it is read back: ``run.py``. Training is safe to leave running: a
checkpoint (``checkpoint.py``) is written atomically every ``checkpoint_every`` steps, and a killed run
started again with the same command ends as an uninterrupted one would; a non-finite loss, gradient or
parameter restores the last good state with the learning rates lowered once, and stops the second time
(``guard.py``); Ctrl-C ends the step, saves and raises KeyboardInterrupt; ``RUN/.lock`` refuses a second
training into the folder while one runs.
"""

from __future__ import annotations

import dataclasses
import json
import math
import random
import time
from collections import defaultdict
from pathlib import Path

import torch
from tqdm import tqdm

from ..config import TrainConfig, validate
from ..data.cameras import scene_extent_from_cameras
from ..data.dataset import ViewDataset, frame_interval
from ..data.frames import DatasetError
from ..data.scene import load_scene
from ..extrapolate import calibrate
from ..machine import resolve_device
from ..models.trace import TraceModel
from ..run import (
    CHECKPOINT,
    CONFIG,
    EXTRAPOLATION,
    LOG,
    SUMMARY,
    RunError,
    fields_in_bf16,
    load_extrapolation,
    load_tensors,
    lock_run,
    save_config,
    save_extrapolation,
    truncate_log,
)
from ..utils import atomic_write_text, remove_temporaries, seed_everything, synchronize
from .checkpoint import (
    Checkpoints,
    check_resumable,
    restore_after,
    restore_trainer_state,
    start_from,
    trainer_state,
    training_fingerprint,
)
from .foreground import hold_surroundings, mark_outside_masks
from .guard import NonFinite, check_parameters, check_step, interrupt_at_step_end
from .init import initial_gaussians
from .losses import views_loss
from .optim import (
    colour_optimizer,
    field_lrs,
    field_optimizer,
    gaussian_lrs,
    gaussian_optimizers,
    means_lr,
    set_group_lrs,
    set_lr,
    step_adams,
    zero_grads,
)
from .report import describe, report_step, stage, summary
from .scene_frame import capture_scale, default_aabb, field_frame
from .strategy import DefaultStrategy
from .threads import ThreadPolicy


class Trainer:
    """Trains one run; ``Trainer(cfg).train()`` is what ``tracegs train`` does. A run folder that holds a
    checkpoint is resumed from it (same settings and images); else ``warm_start``'s model is the start."""

    def __init__(self, cfg: TrainConfig, progress: bool = True, warm_start: Path | None = None):
        validate(cfg)
        # the run records where its data is absolutely: commands started elsewhere find it
        cfg = dataclasses.replace(cfg, data=Path(cfg.data).resolve(), run=Path(cfg.run).resolve())
        self.cfg, self.progress = cfg, progress
        self.device = resolve_device(cfg.device)
        self.generator = seed_everything(cfg.seed)
        self.run = cfg.run
        if self.run.exists() and not self.run.is_dir():
            raise RunError(f"{self.run}: not a folder; --run names the folder a run is written to")
        if cfg.t_train_end is not None:
            self.t_train_end = cfg.t_train_end
        else:  # the dataset's own value (tracegs synth writes it), else every training frame
            self.t_train_end = load_scene(cfg.data, "train", cfg.downscale).t_train_end
        self.data = ViewDataset(
            cfg.data,
            "train",
            cfg.downscale,
            t_max=self.t_train_end,
            device=self.device,
            arriving=cfg.arriving_frames,
        )
        if len(self.data) == 0:
            raise DatasetError(f"{cfg.data}: no training frames with time <= {self.t_train_end}")
        self.fingerprint = training_fingerprint(self.data)
        times = self.data.times
        self.t_max = float(times.max())
        self.dt_frame = frame_interval(times, self.data.scene.fps)
        self.extent = scene_extent_from_cameras(self.data.camera_centers())
        self.aabb = default_aabb(cfg, self.data).to(self.device)
        self.static_views = self._static_views()
        self._allowed: tuple = (None, [])  # the views of the current time range (``_dynamic_view``)
        self.static_fraction: float | None = None  # of the Gaussians marked static (stage2.skip_static)
        log = tqdm.write if progress else (lambda _message: None)
        gaussians = initial_gaussians(cfg, self.aabb, self.device, log, self.data.scene.frames)
        cameras = sorted({v.camera_id for v in self.data.views if v.camera_id is not None})
        settings = cfg.model_config()
        self.model = TraceModel(settings, gaussians, self.aabb, self.dt_frame, cameras).to(self.device)
        self.model.bf16 = fields_in_bf16(cfg)  # (not cfg.bf16 alone: a config made on another CPU)
        self.model.set_field_frame(*field_frame(cfg, self.data))
        self.model.set_near_plane(cfg.near_plane * capture_scale(self.data))
        self.optimizers = gaussian_optimizers(self.model.gaussians, cfg.optim, self.extent)
        self.field_opt = field_optimizer(self.model.field_parameter_groups(), cfg.optim)
        self.colour_opt = colour_optimizer(self.model.camera_colour, cfg.optim)
        counts = sorted(len(v) for v in self.data.by_time().values())  # cameras per time
        self.views_per_step = max(1, min(cfg.stage2.views_per_step, counts[len(counts) // 2]))
        views = cfg.dynamic_iterations * cfg.stage2.views_per_step  # as many where fewer cameras saw a time
        self.dynamic_steps = 0 if cfg.method == "static" else math.ceil(views / self.views_per_step)
        self.total_steps = cfg.static_iterations + self.dynamic_steps
        self.strategy = DefaultStrategy(cfg.densify, self.extent, self.total_steps)
        self.strategy_state = self.strategy.initialize_state()
        self.step, self.train_seconds = 0, 0.0
        self.lr_scale = 1.0  # lowered by the NaN guard
        self.restorations: list[dict] = []  # what the NaN guard restored: {"step", "to_step", "what"}
        self.extrapolation = None  # the post-training state (``extrapolate.calibrate``), once trained
        self.timings: dict[str, float] = defaultdict(float)
        self.checkpoints = Checkpoints(self.run / CHECKPOINT)
        self._in_step = False  # while a step runs: an interrupt then leaves half a step
        self.threads: ThreadPolicy | None = None  # the thread counts of the steps this call trains
        if (self.run / CHECKPOINT).is_file():
            self._resume(self.run / CHECKPOINT)
        elif warm_start is not None:  # a continual round (``continual.py``) goes on from the last one's model
            start_from(self, Path(warm_start) / CHECKPOINT)

    # ----- data ---------------------------------------------------------------------------------
    def _static_views(self) -> list[int]:
        """Stage 1 uses the images at the first time if at least 3 cameras saw it (multi-view
        capture), else all training images (a monocular video has a single view per time)."""
        t0 = min(v.time for v in self.data.views)
        first = [i for i, v in enumerate(self.data.views) if abs(v.time - t0) < 1e-9]
        return first if len(first) >= 3 else list(range(len(self.data)))

    def time_limit(self, dyn_step: int) -> float:
        """End of the sampled time range at a dynamic step: it grows in ``stage2.time_growth_stages``
        equal steps over the first ``stage2.time_growth_fraction`` of the stage."""
        growth = self.cfg.stage2.time_growth_fraction * self.dynamic_steps
        stages = self.cfg.stage2.time_growth_stages
        frac = 1.0 if growth <= 0 else min(1.0, (1 + (stages * dyn_step) // growth) / stages)
        return self.t_max * frac

    def _dynamic_view(self, dyn_step: int) -> int:
        """A training image whose time lies in the current (growing) time range."""
        limit = self.time_limit(dyn_step) + 1e-9
        key = (limit, id(self.data), len(self.data.views))  # (the list changes with the time range only)
        if self._allowed[0] != key:
            self._allowed = (key, [i for i, v in enumerate(self.data.views) if v.time <= limit])
        return random.choice(self._allowed[1])

    def _views_at_time(self, index: int) -> list:
        """View ``index`` and up to ``views_per_step`` - 1 other cameras' views at its time, at random."""
        extra, chosen = self.views_per_step - 1, []
        if extra > 0:  # (the one-view step looks up nothing)
            others = self.data.same_time(index)
            chosen = random.sample(others, min(extra, len(others)))
        return [self.data[i] for i in [index, *chosen]]

    def _t_prime(self, t: float) -> float:
        """t' = t -/+ dt with a random sign, kept inside [0, t_max]."""
        dt = self.cfg.stage2.dt_frames * self.dt_frame
        sign = random.choice((-1.0, 1.0))
        t_prime = t - sign * dt
        if not 0.0 <= t_prime <= self.t_max:
            t_prime = t + sign * dt
        return min(max(t_prime, 0.0), self.t_max)

    def _consistency_time(self, t_prime: float, t: float, limit: float) -> float:
        """Where the acceleration consistency reads f_trd again: ``stage2.consistency_frames`` frame
        intervals from t' in the direction of t (the other way where that leaves [0, ``limit``],
        clamped), or t itself when the setting is 0."""
        frames = self.cfg.stage2.consistency_frames
        if frames <= 0 or t == t_prime:
            return t
        span = math.copysign(frames * self.dt_frame, t - t_prime)
        t_check = t_prime + span
        if not 0.0 <= t_check <= limit:
            t_check = t_prime - span
        return min(max(t_check, 0.0), max(limit, t))

    def _static_marking_step(self) -> int:
        """Step at which ``stage2.skip_static`` marks the static Gaussians: densification has stopped
        (the set of Gaussians is final) and the sampled time range covers the training span."""
        growth = math.ceil(self.cfg.stage2.time_growth_fraction * self.dynamic_steps)
        return max(self.strategy.refine_stop, self.cfg.static_iterations + growth)

    # ----- one step -------------------------------------------------------------------------------
    def _set_lrs(self, static: bool, step: int, dyn_step: int) -> None:
        """This step's learning rates (the schedules of ``optim.py``) times the NaN guard's ``lr_scale``."""
        cfg, scale = self.cfg, self.lr_scale
        lrs = gaussian_lrs(cfg.optim, self.extent)
        lrs["means"] = means_lr(cfg.optim, self.extent, step, self.total_steps)
        for name, opt in self.optimizers.items():
            set_lr(opt, lrs[name] * scale)
        if not static:
            fields = field_lrs(cfg.optim, self.extent, dyn_step, self.dynamic_steps)
            set_group_lrs(self.field_opt, {k: v * scale for k, v in fields.items()})

    def _zero_grads(self) -> None:
        zero_grads([*self.optimizers.values(), self.field_opt, self.colour_opt])

    def sh_degree(self) -> int:
        return min(self.cfg.sh_degree, self.step // max(self.cfg.sh_degree_interval, 1))

    def _clock(self) -> float:
        """Wall time for the per-part timings; on CUDA after the queued kernels finish (their own time)."""
        synchronize(self.device)
        return time.perf_counter()

    def train_step(self) -> dict[str, float]:
        """One step; NonFinite (with nothing updated) when the loss or a gradient is not finite."""
        self._in_step = True
        try:
            stats = self._step()
        except NonFinite:
            self._in_step = False
            raise
        self._in_step = False
        return stats

    def views_loss(self, state: dict, views: list, background: torch.Tensor) -> tuple[dict, list[dict]]:
        """The loss terms of Gaussians ``state`` rendered from ``views`` (``losses.views_loss``)."""
        return views_loss(self, state, views, background)

    def _step(self) -> dict[str, float]:
        cfg, step = self.cfg, self.step
        static = step < cfg.static_iterations or cfg.method == "static"
        dyn_step = step - cfg.static_iterations
        self._set_lrs(static, step, dyn_step)

        t_start = self._clock()
        if static:
            views = [self.data[random.choice(self.static_views)]]
            g = self.model.gaussians
            state = {"means": g["means"], "quats": g["quats"], "scales": g["scales"]}
        else:
            if dyn_step == 0:
                self.model.begin_dynamic_stage()
                if cfg.stage2.static_outside_masks:
                    self.static_fraction = mark_outside_masks(self, tqdm.write if self.progress else len)
            skip = cfg.stage2.skip_static
            if skip and self.model.static_mask is None and step == self._static_marking_step():
                threshold = cfg.stage2.static_displacement * self.extent
                self.static_fraction = self.model.mark_static(
                    threshold, self.t_max, margin=cfg.stage2.static_margin
                )
            views = self._views_at_time(self._dynamic_view(dyn_step))
            view = views[0]
            t_prime = self._t_prime(view.time)
            t_check = self._consistency_time(t_prime, view.time, self.time_limit(dyn_step))
            state, extra_losses = self.model.training_state(t_prime, view.time, t_check=t_check)
        t_fields = self._clock()
        background = torch.rand(3, device=self.device) if cfg.random_background else self.data.background
        losses, infos = self.views_loss(state, views, background)
        if not static:  # the model's named auxiliary losses join the loss, each logged by name
            for name, value in (extra_losses | self.model.regularization_losses()).items():
                losses[name] = value
                losses["loss"] = losses["loss"] + value
        t_render = self._clock()
        losses["loss"].backward()
        try:
            check_step(losses["loss"], self.model.parameters(), step)
        except NonFinite:
            self._zero_grads()
            raise
        t_backward = self._clock()
        if not static and cfg.stage2.freeze_surroundings:
            hold_surroundings(self)
        gaussians = list(self.optimizers.values())
        step_adams([*gaussians, None if static else self.field_opt, self.colour_opt])
        zero_grads([*gaussians, self.field_opt, self.colour_opt])
        report = self.strategy.step_post_backward(
            self.model.gaussians, self.optimizers, self.strategy_state, step, infos
        )
        t_end = self._clock()
        for key, dt in (
            ("fields", t_fields - t_start),
            ("raster_forward", t_render - t_fields),
            ("backward", t_backward - t_render),
            ("optimizer", t_end - t_backward),
        ):
            self.timings[key] += dt
        self.train_seconds += t_end - t_start
        self.step += 1
        return {k: float(v.detach()) for k, v in losses.items()} | {f"n_{k}": v for k, v in report.items()}

    # ----- loop -------------------------------------------------------------------------------------
    def train(self) -> dict:
        """Train the remaining steps (all of them for a new run), calibrate the extrapolation state and
        write the summary. Holds ``RUN/.lock`` throughout: a second training into the folder is refused."""
        self.run.mkdir(parents=True, exist_ok=True)
        with lock_run(self.run):
            for name in (CHECKPOINT, CONFIG, EXTRAPOLATION, LOG, SUMMARY):  # of a killed process's writes
                remove_temporaries(self.run / name)
            save_config(self.cfg, self.run / CONFIG)
            truncate_log(self.run / LOG, self.step)  # the steps past the checkpoint are trained again
            if self.progress:
                tqdm.write(self.describe())
            self.checkpoints.keep(trainer_state(self))
            ran = self._train_steps()
            if not ran:  # a finished run: its checkpoint takes the config of this call
                self.save()
            if self.extrapolation is None:  # (a finished run resumed with the same settings keeps its own)
                self.extrapolation = calibrate(self.model, self.t_max, self.extent)
                save_extrapolation(self.run, self.extrapolation)
            summary = self.summary()
            atomic_write_text(self.run / SUMMARY, json.dumps(summary, indent=2))
        return summary

    def _train_steps(self) -> bool:
        """The steps up to ``total_steps``, each checkpoint and the last one saved; whether any ran."""
        cfg, total, start = self.cfg, self.total_steps, self.step
        self._in_step = False
        bar = tqdm(total=total, initial=self.step, disable=not self.progress, desc=f"train {stage(self)}")
        log = (self.run / LOG).open("a")
        try:
            with interrupt_at_step_end() as interrupt, ThreadPolicy(cfg.threads) as threads:
                self.threads = threads
                while self.step < total:
                    try:
                        threads.check()
                        stats = self.train_step()
                        report_step(self, stats, bar, log)
                        if self.step % cfg.checkpoint_every == 0 or self.step == total:
                            check_parameters(self.model.parameters(), self.step)
                            self.save()
                    except NonFinite as err:
                        log.close()
                        restore_after(self, err)
                        log = (self.run / LOG).open("a")
                        bar.reset(total)
                        bar.update(self.step)
                    if interrupt.requested:
                        raise KeyboardInterrupt
        except KeyboardInterrupt:
            self._save_interrupted()
            raise
        finally:
            bar.close()
            log.close()
        return self.step > start

    def _save_interrupted(self) -> None:
        """The checkpoint of an interrupted run: the current step's, or the last good state where the
        interrupt came in the middle of a step or the parameters are not finite."""
        held = f"step {self.step}"
        try:
            if self._in_step:
                raise NonFinite(self.step, "step")  # half a step: neither this one nor the next
            check_parameters(self.model.parameters(), self.step)
            self.save()
        except NonFinite:
            self.checkpoints.write_good()
            held = "the last good state"
        finally:
            self._in_step = False
        if self.progress:
            tqdm.write(f"interrupted: {self.run / CHECKPOINT} holds {held}; the same command resumes")

    def describe(self) -> str:  # what this run trains, in a line or two (printed when it starts)
        return describe(self)

    def summary(self) -> dict:
        return summary(self)

    # ----- checkpoints -----------------------------------------------------------------------------
    def save(self) -> Path:
        """Write the checkpoint (atomically) and keep it in memory as the last good state."""
        return self.checkpoints.save(trainer_state(self))

    def _resume(self, path: Path) -> None:
        ckpt = load_tensors(path, self.device)
        changed = check_resumable(ckpt, self.cfg, self.fingerprint, path)
        restore_trainer_state(self, ckpt)
        if not changed:  # else calibrated again with the new settings when the steps are done
            self.extrapolation = load_extrapolation(self.run, self.device)
