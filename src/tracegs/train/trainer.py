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
import time
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
    TrainingDiverged,
    fields_in_bf16,
    load_extrapolation,
    load_tensors,
    lock_run,
    save_config,
    save_extrapolation,
    truncate_log,
)
from ..utils import atomic_write_text, remove_temporaries, seed_everything, synchronize
from .checkpoint import Checkpoints, check_resumable, checkpoint, restore, start_from, training_fingerprint
from .foreground import hold_surroundings, mark_outside_masks
from .guard import NonFinite, check_parameters, check_step, diverged, interrupt_at_step_end
from .init import initial_gaussians
from .losses import ForegroundMasks, views_loss
from .optim import field_lrs, gaussian_lrs, means_lr, set_group_lrs, set_lr, step_adams, zero_grads
from .report import describe, report_step, stage, summary
from .sampling import StepSampler, dynamic_steps, views_per_step
from .scene_frame import capture_scale, default_aabb, field_frame
from .state import TrainState
from .strategy import DefaultStrategy
from .threads import ThreadPolicy


class Trainer:
    """Trains one run; ``Trainer(cfg).train()`` is what ``tracegs train`` does. A run folder that holds a
    checkpoint is resumed from it (same settings and images); else ``warm_start``'s model is the start.
    What changes as it trains is ``state`` (``TrainState``, saved whole in the checkpoint); the rest
    (settings, data, model, sampler, strategy) it composes and hands to the functions of ``train/``."""

    def __init__(self, cfg: TrainConfig, progress: bool = True, warm_start: Path | None = None):
        validate(cfg)
        # the run records where its data is absolutely: commands started elsewhere find it
        cfg = dataclasses.replace(cfg, data=Path(cfg.data).resolve(), run=Path(cfg.run).resolve())
        self.cfg, self.progress = cfg, progress
        self.device = resolve_device(cfg.device)
        generator = seed_everything(cfg.seed)
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
        self.masks = ForegroundMasks(cfg.data)  # (read when the mask loss first needs them)
        log = tqdm.write if progress else (lambda _message: None)
        gaussians = initial_gaussians(cfg, self.aabb, self.device, log, self.data.scene.frames)
        cameras = sorted({v.camera_id for v in self.data.views if v.camera_id is not None})
        settings = cfg.model_config()
        self.model = TraceModel(settings, gaussians, self.aabb, self.dt_frame, cameras).to(self.device)
        self.model.bf16 = fields_in_bf16(cfg)  # (not cfg.bf16 alone: a config made on another CPU)
        self.model.set_field_frame(*field_frame(cfg, self.data))
        self.model.set_near_plane(cfg.near_plane * capture_scale(self.data))
        per_step = views_per_step(self.data, cfg.stage2)
        self.dynamic_steps = dynamic_steps(cfg.method, cfg.dynamic_iterations, cfg.stage2, per_step)
        self.total_steps = cfg.static_iterations + self.dynamic_steps
        self.sampler = StepSampler(
            self.data, cfg.stage2, self.dynamic_steps, per_step, self.t_max, self.dt_frame
        )
        self.strategy = DefaultStrategy(cfg.densify, self.extent, self.total_steps)
        self.extrapolation = None  # the post-training state (``extrapolate.calibrate``), once trained
        self.checkpoints = Checkpoints(self.run / CHECKPOINT)
        self._in_step = False  # while a step runs: an interrupt then leaves half a step
        self.threads: ThreadPolicy | None = None  # the thread counts of the steps this call trains
        if warm_start is not None and not (self.run / CHECKPOINT).is_file():
            # a continual round (``continual.py``) goes on from the last one's model
            start_from(self.model, Path(warm_start) / CHECKPOINT, self.device)
        self.state = TrainState.start(self.model, cfg.optim, self.extent, self.strategy, generator)
        if (self.run / CHECKPOINT).is_file():
            self._resume(self.run / CHECKPOINT)

    # ----- one step -------------------------------------------------------------------------------
    def _static_marking_step(self) -> int:
        """Step at which ``stage2.skip_static`` marks the static Gaussians: densification has stopped
        (the set of Gaussians is final) and the sampled time range covers the training span."""
        return max(self.strategy.refine_stop, self.cfg.static_iterations + self.sampler.growth_steps())

    def _set_lrs(self, static: bool, step: int, dyn_step: int) -> None:
        """This step's learning rates (the schedules of ``optim.py``) times the NaN guard's ``lr_scale``."""
        cfg, scale = self.cfg, self.state.lr_scale
        lrs = gaussian_lrs(cfg.optim, self.extent)
        lrs["means"] = means_lr(cfg.optim, self.extent, step, self.total_steps)
        for name, opt in self.state.optimizers.items():
            set_lr(opt, lrs[name] * scale)
        if not static:
            fields = field_lrs(cfg.optim, self.extent, dyn_step, self.dynamic_steps)
            set_group_lrs(self.state.field_opt, {k: v * scale for k, v in fields.items()})

    def sh_degree(self) -> int:
        return min(self.cfg.sh_degree, self.state.step // max(self.cfg.sh_degree_interval, 1))

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
        targets = self.data if self.cfg.random_background else None
        optim, strategy = self.cfg.optim, self.strategy
        return views_loss(
            self.model, state, views, background, self.sh_degree(), optim, strategy, targets, self.masks
        )

    def _mark_static(self, step: int, dyn_step: int) -> None:
        """Hold the surroundings static where stage 2 starts (``stage2.static_outside_masks``), and the
        Gaussians that hardly move at ``_static_marking_step`` (``stage2.skip_static``)."""
        cfg, model = self.cfg, self.model
        if dyn_step == 0 and cfg.stage2.static_outside_masks:
            frames = [f for f in self.data.scene.frames if f.time <= self.t_max + 1e-9]
            log = tqdm.write if self.progress else len
            margin = cfg.stage2.static_margin
            self.state.static_fraction = mark_outside_masks(model, cfg.data, frames, margin, log)
        if cfg.stage2.skip_static and model.static_mask is None and step == self._static_marking_step():
            threshold = cfg.stage2.static_displacement * self.extent
            self.state.static_fraction = model.mark_static(
                threshold, self.t_max, margin=cfg.stage2.static_margin
            )

    def _step(self) -> dict[str, float]:
        cfg, state, sampler = self.cfg, self.state, self.sampler
        step = state.step
        static = step < cfg.static_iterations or cfg.method == "static"
        dyn_step = step - cfg.static_iterations
        self._set_lrs(static, step, dyn_step)

        t_start = self._clock()
        if static:
            views = [self.data[sampler.static_view()]]
            g = self.model.gaussians
            gaussians = {"means": g["means"], "quats": g["quats"], "scales": g["scales"]}
        else:
            if dyn_step == 0:
                self.model.begin_dynamic_stage()
            self._mark_static(step, dyn_step)
            views = sampler.views_at_time(sampler.dynamic_view(dyn_step))
            view = views[0]
            t_prime = sampler.t_prime(view.time)
            t_check = sampler.consistency_time(t_prime, view.time, sampler.time_limit(dyn_step))
            gaussians, extra_losses = self.model.training_state(t_prime, view.time, t_check=t_check)
        t_fields = self._clock()
        background = torch.rand(3, device=self.device) if cfg.random_background else self.data.background
        losses, infos = self.views_loss(gaussians, views, background)
        if not static:  # the model's named auxiliary losses join the loss, each logged by name
            for name, value in (extra_losses | self.model.regularization_losses()).items():
                losses[name] = value
                losses["loss"] = losses["loss"] + value
        t_render = self._clock()
        losses["loss"].backward()
        try:
            check_step(losses["loss"], self.model.parameters(), step)
        except NonFinite:
            zero_grads(state.all_optimizers())
            raise
        t_backward = self._clock()
        if not static and cfg.stage2.freeze_surroundings:
            hold_surroundings(self.model, state.optimizers)
        adams = list(state.optimizers.values())
        step_adams([*adams, None if static else state.field_opt, state.colour_opt])
        zero_grads(state.all_optimizers())
        report = self.strategy.step_post_backward(
            self.model.gaussians, state.optimizers, state.strategy, step, infos
        )
        if not static:  # stage 2 densifies what moves until densify.moving_refine_stop
            held = self.model.static_mask
            moved, grown = self.strategy.refine_moving(
                self.model.gaussians, state.optimizers, state.strategy, step, infos, held
            )
            if moved:
                report = moved
                self.model.set_static_mask(grown)
        t_end = self._clock()
        for key, dt in (
            ("fields", t_fields - t_start),
            ("raster_forward", t_render - t_fields),
            ("backward", t_backward - t_render),
            ("optimizer", t_end - t_backward),
        ):
            state.timings[key] += dt
        state.train_seconds += t_end - t_start
        state.step += 1
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
            truncate_log(self.run / LOG, self.state.step)  # the steps past the checkpoint are trained again
            if self.progress:
                tqdm.write(self.describe())
            self.checkpoints.keep(self._checkpoint())
            ran = self._train_steps()
            if not ran:  # a finished run: its checkpoint takes the config of this call
                self.save()
            if self.extrapolation is None:  # (a finished run resumed with the same settings keeps its own)
                cfg = self.cfg
                predictor = calibrate(
                    self.model, self.t_max, cfg.extrapolation, cfg.data, cfg.downscale, self.extent
                )
                self.extrapolation = predictor.state
                save_extrapolation(self.run, self.extrapolation)
            summary = self.summary()
            atomic_write_text(self.run / SUMMARY, json.dumps(summary, indent=2))
        return summary

    def _train_steps(self) -> bool:
        """The steps up to ``total_steps``, each checkpoint and the last one saved; whether any ran."""
        cfg, total, start = self.cfg, self.total_steps, self.state.step
        self._in_step = False
        bar = tqdm(total=total, initial=start, disable=not self.progress, desc=f"train {stage(cfg, start)}")
        log = (self.run / LOG).open("a")
        try:
            with interrupt_at_step_end() as interrupt, ThreadPolicy(cfg.threads) as threads:
                self.threads = threads
                while self.state.step < total:
                    try:
                        threads.check()
                        stats = self.train_step()
                        n = self.model.gaussians["means"].shape[0]
                        report_step(cfg, self.state, total, n, stats, bar, log)
                        if self.state.step % cfg.checkpoint_every == 0 or self.state.step == total:
                            check_parameters(self.model.parameters(), self.state.step)
                            self.save()
                    except NonFinite as err:
                        log.close()
                        self._restore_after(err)
                        log = (self.run / LOG).open("a")
                        bar.reset(total)
                        bar.update(self.state.step)
                    if interrupt.requested:
                        raise KeyboardInterrupt
        except KeyboardInterrupt:
            self._save_interrupted()
            raise
        finally:
            bar.close()
            log.close()
        return self.state.step > start

    def _save_interrupted(self) -> None:
        """The checkpoint of an interrupted run: the current step's, or the last good state where the
        interrupt came in the middle of a step or the parameters are not finite."""
        held = f"step {self.state.step}"
        try:
            if self._in_step:
                raise NonFinite(self.state.step, "step")  # half a step: neither this one nor the next
            check_parameters(self.model.parameters(), self.state.step)
            self.save()
        except NonFinite:
            self.checkpoints.write_good()
            held = "the last good state"
        finally:
            self._in_step = False
        if self.progress:
            tqdm.write(f"interrupted: {self.run / CHECKPOINT} holds {held}; the same command resumes")

    def describe(self) -> str:  # what this run trains, in a line or two (printed when it starts)
        cfg, model, device = self.cfg, self.model, self.device
        per_step = self.sampler.views_per_step
        return describe(cfg, self.data, model, self.t_max, self.total_steps, per_step, device)

    def summary(self) -> dict:
        cfg, model, device = self.cfg, self.model, self.device
        return summary(cfg, self.state, model, self.t_max, self.extrapolation, device, self.threads)

    # ----- checkpoints -----------------------------------------------------------------------------
    def _checkpoint(self) -> dict:
        return checkpoint(self.state, self.model, self.cfg, self.fingerprint, self.t_max, self.device)

    def save(self) -> Path:
        """Write the checkpoint (atomically) and keep it in memory as the last good state."""
        return self.checkpoints.save(self._checkpoint())

    def _restore(self, ckpt: dict) -> None:
        """The model and ``state`` as the checkpoint ``ckpt`` holds them."""
        cfg, generator = self.cfg, self.state.generator
        self.state = restore(ckpt, self.model, cfg.optim, self.extent, self.strategy, generator, self.device)

    def _resume(self, path: Path) -> None:
        ckpt = load_tensors(path, self.device)
        changed = check_resumable(ckpt, self.cfg, self.fingerprint, path)
        self._restore(ckpt)
        if not changed:  # else calibrated again with the new settings when the steps are done
            self.extrapolation = load_extrapolation(self.run, self.device)

    def _restore_after(self, err: NonFinite) -> None:
        """The NaN guard after ``err``: back to the last good state with the learning rates times
        ``optim.nan_lr_factor``; the second time, that state is saved and ``TrainingDiverged`` raised."""
        failed, factor = self.state, self.cfg.optim.nan_lr_factor
        self._restore(self.checkpoints.last_good(self.device))
        self.state.train_seconds = failed.train_seconds  # the time spent is spent
        truncate_log(self.run / LOG, self.state.step)
        if failed.restorations:
            self.save()
            raise TrainingDiverged(
                diverged(self.run / CHECKPOINT, err, failed.restorations[0], factor, self.state.step)
            )
        self.state.lr_scale = failed.lr_scale * factor
        self.state.restorations = [
            *failed.restorations,
            {"step": err.step, "to_step": self.state.step, "what": err.what},
        ]
        if self.progress:
            tqdm.write(f"{err}: restored step {self.state.step}, learning rates x{factor}")
