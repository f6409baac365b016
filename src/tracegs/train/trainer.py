"""The training loop: stage 1 (static 3DGS at t = 0), stage 2 (TRACE or DefGS), checkpoints, resume,
and the post-training calibration of the extrapolation state when the last step is done.

What the run folder holds, and how it is read back: ``run.py``. A checkpoint is written atomically
every ``checkpoint_every`` steps; a killed run resumes from it.
"""

from __future__ import annotations

import json
import math
import random
import time
from collections import defaultdict
from pathlib import Path

import torch
from tqdm import tqdm

from ..config import TrainConfig, config_to_dict
from ..data.cameras import scene_extent_from_cameras
from ..data.dataset import ViewDataset, frame_interval
from ..data.scene import load_scene
from ..extrapolate import calibrate
from ..models.gaussians import create_gaussians, random_gaussians
from ..models.trace import TraceModel
from ..render.rendering import resolve_backend
from ..run import (
    CHECKPOINT,
    CONFIG,
    LOG,
    SUMMARY,
    changed_settings,
    gaussians_of,
    load_extrapolation,
    load_tensors,
    save_config,
    save_extrapolation,
    save_tensors,
    training_changes,
)
from ..utils import atomic_write_text, resolve_device, seed_everything, synchronize
from .losses import photometric_loss
from .optim import field_lrs, field_optimizer, gaussian_optimizers, means_lr, set_group_lrs, set_lr
from .scene_frame import default_aabb, field_frame
from .strategy import DefaultStrategy


def initial_gaussians(cfg: TrainConfig, aabb: torch.Tensor, device) -> torch.nn.ParameterDict:
    """From ``points3d.ply`` in the scene folder if there is one (SfM points), else random in ``aabb``."""
    ply = Path(cfg.data) / "points3d.ply"
    if ply.is_file():
        from ..data.points import read_points

        points, colors = read_points(ply)
        return create_gaussians(points.to(device), colors.to(device), cfg.sh_degree)
    return random_gaussians(cfg.init_points, aabb, cfg.sh_degree)


class Trainer:
    """Trains one run; ``Trainer(cfg).train()`` is what ``tracegs train`` does."""

    def __init__(self, cfg: TrainConfig, progress: bool = True):
        self.cfg, self.progress = cfg, progress
        if cfg.stage2.time_growth_stages < 1:
            raise ValueError(f"stage2.time_growth_stages must be >= 1, got {cfg.stage2.time_growth_stages}")
        self.device = resolve_device(cfg.device)
        self.generator = seed_everything(cfg.seed)
        self.run = Path(cfg.run)
        if cfg.t_train_end is not None:
            self.t_train_end = cfg.t_train_end
        else:  # the dataset's own value (tracegs synth writes it), else every training frame
            self.t_train_end = load_scene(cfg.data, "train", cfg.downscale).t_train_end
        self.data = ViewDataset(cfg.data, "train", cfg.downscale, t_max=self.t_train_end, device=self.device)
        if len(self.data) == 0:
            raise ValueError(f"{cfg.data}: no training frames with time <= {self.t_train_end}")
        times = self.data.times
        self.t_max = float(times.max())
        self.dt_frame = frame_interval(times, self.data.scene.fps)
        self.extent = scene_extent_from_cameras(self.data.camera_centers())
        self.aabb = default_aabb(cfg, self.data).to(self.device)
        self.static_views = self._static_views()
        self.static_fraction: float | None = None  # of the Gaussians marked static (stage2.skip_static)
        gaussians = initial_gaussians(cfg, self.aabb, self.device)
        self.model = TraceModel(cfg, gaussians, self.aabb, self.dt_frame).to(self.device)
        self.model.set_field_frame(*field_frame(cfg, self.data))
        self.optimizers = gaussian_optimizers(self.model.gaussians, cfg.optim, self.extent)
        self.field_opt = field_optimizer(self.model.field_parameter_groups(), cfg.optim)
        self.strategy = DefaultStrategy(cfg.densify, self.extent, cfg.total_iterations)
        self.strategy_state = self.strategy.initialize_state()
        self.step, self.train_seconds = 0, 0.0
        self.extrapolation = None  # the post-training state (``extrapolate.calibrate``), once trained
        self.timings: dict[str, float] = defaultdict(float)
        if (self.run / CHECKPOINT).is_file():
            self._resume(self.run / CHECKPOINT)

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
        growth = self.cfg.stage2.time_growth_fraction * self.cfg.dynamic_iterations
        stages = self.cfg.stage2.time_growth_stages
        frac = 1.0 if growth <= 0 else min(1.0, (1 + (stages * dyn_step) // growth) / stages)
        return self.t_max * frac

    def _dynamic_view(self, dyn_step: int) -> int:
        """A training image whose time lies in the current (growing) time range."""
        limit = self.time_limit(dyn_step) + 1e-9
        allowed = [i for i, v in enumerate(self.data.views) if v.time <= limit]
        return random.choice(allowed)

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
        growth = math.ceil(self.cfg.stage2.time_growth_fraction * self.cfg.dynamic_iterations)
        return max(self.strategy.refine_stop, self.cfg.static_iterations + growth)

    # ----- one step -------------------------------------------------------------------------------
    def sh_degree(self) -> int:
        return min(self.cfg.sh_degree, self.step // max(self.cfg.sh_degree_interval, 1))

    def _clock(self) -> float:
        """Wall time for the per-part timings; on CUDA after the queued kernels finish, so that each
        part is charged its own GPU time rather than the time to queue it."""
        synchronize(self.device)
        return time.perf_counter()

    def train_step(self) -> dict[str, float]:
        cfg, step = self.cfg, self.step
        static = step < cfg.static_iterations or cfg.method == "static"
        dyn_step = step - cfg.static_iterations
        total = cfg.total_iterations
        set_lr(self.optimizers["means"], means_lr(cfg.optim, self.extent, step, total))
        if not static:
            set_group_lrs(self.field_opt, field_lrs(cfg.optim, self.extent, dyn_step, cfg.dynamic_iterations))

        t_start = self._clock()
        if static:
            view = self.data[random.choice(self.static_views)]
            g = self.model.gaussians
            state = {"means": g["means"], "quats": g["quats"], "scales": g["scales"]}
        else:
            if dyn_step == 0:
                self.model.begin_dynamic_stage()
            skip = cfg.stage2.skip_static
            if skip and self.model.static_mask is None and step == self._static_marking_step():
                threshold = cfg.stage2.static_displacement * self.extent
                self.static_fraction = self.model.mark_static(threshold, self.t_max)
            view = self.data[self._dynamic_view(dyn_step)]
            t_prime = self._t_prime(view.time)
            t_check = self._consistency_time(t_prime, view.time, self.time_limit(dyn_step))
            state, extra_losses = self.model.training_state(t_prime, view.time, t_check=t_check)
        t_fields = self._clock()
        if cfg.random_background:
            background = torch.rand(3, device=self.device)
            target = self.data.target(view, background)
        else:
            background, target = self.data.background, view.image
        out = self.model.render(state, view.camera, self.sh_degree(), background)
        info = {
            "means2d": out.means2d,
            "radii": out.radii,
            "width": view.camera.width,
            "height": view.camera.height,
        }
        self.strategy.step_pre_backward(info)
        losses = photometric_loss(out.image, target, cfg.optim.ssim_weight)
        if not static:  # the model's named auxiliary losses join the loss, each logged by name
            for name, value in (extra_losses | self.model.regularization_losses()).items():
                losses[name] = value
                losses["loss"] = losses["loss"] + value
        t_render = self._clock()
        losses["loss"].backward()
        t_backward = self._clock()
        for opt in self.optimizers.values():
            opt.step()
            opt.zero_grad(set_to_none=True)
        if not static and self.field_opt is not None:
            self.field_opt.step()
        if self.field_opt is not None:
            self.field_opt.zero_grad(set_to_none=True)
        report = self.strategy.step_post_backward(
            self.model.gaussians, self.optimizers, self.strategy_state, step, info
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
        cfg = self.cfg
        self.run.mkdir(parents=True, exist_ok=True)
        save_config(cfg, self.run / CONFIG)
        total = cfg.total_iterations
        if self.progress:
            tqdm.write(self.describe())
        bar = tqdm(total=total, initial=self.step, disable=not self.progress, desc=f"train {cfg.method}")
        log = (self.run / LOG).open("a")
        try:
            while self.step < total:
                stats = self.train_step()
                bar.update(1)
                if self.step % cfg.log_every == 0 or self.step == total:
                    n = self.model.gaussians["means"].shape[0]
                    bar.set_postfix(loss=f"{stats['loss']:.4f}", gaussians=n)
                    seconds = round(self.train_seconds, 2)  # training time so far, resumed runs included
                    log.write(
                        json.dumps({"step": self.step, "gaussians": n, "seconds": seconds, **stats}) + "\n"
                    )
                    log.flush()
                if self.step % cfg.checkpoint_every == 0 and self.step < total:
                    self.save()
        finally:
            bar.close()
            log.close()
        self.save()  # the last step (never saved in the loop) is kept if the calibration fails
        if self.extrapolation is None:  # (a finished run resumed with the same settings keeps its own)
            self.extrapolation = calibrate(self.model, self.t_max, self.extent)
            save_extrapolation(self.run, self.extrapolation)
        summary = self.summary()
        atomic_write_text(self.run / SUMMARY, json.dumps(summary, indent=2))
        return summary

    def describe(self) -> str:
        """What this run trains, in a line or two (printed when training starts)."""
        cfg, cam = self.cfg, self.data.views[0].camera
        frame = "world frame" if self.model.fields_see_world else "cameras' frame"
        text = (
            f"{cfg.method} ({cfg.preset}) on {len(self.data)} images of {cam.width}x{cam.height} px with "
            f"t <= {self.t_max:.3g}, {cfg.total_iterations} steps on {self.device} "
            f"({resolve_backend(cfg.backend, self.device)} rasteriser, fields in the {frame})"
        )
        pixels = cam.width * cam.height
        if self.device.type == "cpu" and cfg.preset == "cpu-fast" and pixels > 4 * 128 * 128:
            factor = math.ceil(math.sqrt(pixels / (128 * 128)))
            text += (
                f"\n  note: {cam.width}x{cam.height} is {pixels / (128 * 128):.0f}x the pixels of the 128 px "
                f"cpu-fast is made for, and the rasteriser's time grows with them; --downscale {factor} "
                "trains at about 128 px"
            )
        return text

    def summary(self) -> dict:
        steps, state = max(self.step, 1), self.extrapolation
        return {
            "method": self.cfg.method,
            "preset": self.cfg.preset,
            "scene": str(self.cfg.data),
            "iterations": self.step,
            "gaussians": int(self.model.gaussians["means"].shape[0]),
            "train_seconds": round(self.train_seconds, 2),
            "t_max": self.t_max,
            "freeze_threshold": state.freeze_threshold if state else None,
            "freeze_psnr": state.report.get("freeze_psnr", {}) if state else {},
            "static_fraction": self.static_fraction,
            "free_bodies": state.report.get("free_bodies", []) if state else [],
            "ms_per_iteration": {k: round(1000 * v / steps, 2) for k, v in self.timings.items()},
            "device": str(self.device),
            "rasteriser": resolve_backend(self.cfg.backend, self.device),
        }

    # ----- checkpoints -----------------------------------------------------------------------------
    def save(self) -> Path:
        ckpt = {
            "step": self.step,
            "train_seconds": self.train_seconds,
            "timings": dict(self.timings),
            "config": config_to_dict(self.cfg),
            "t_max": self.t_max,
            "static_mask": self.model.static_mask,
            "model": self.model.state_dict(),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "field_optimizer": self.field_opt.state_dict() if self.field_opt is not None else None,
            "rng": {"torch": torch.get_rng_state(), "python": random.getstate()},
        }
        return save_tensors(ckpt, self.run / CHECKPOINT)

    def _resume(self, path: Path) -> None:
        ckpt = load_tensors(path, self.device)
        try:
            changed = changed_settings(ckpt.get("config", {}), self.cfg)
        except ValueError as err:
            raise ValueError(f"{path}: {err}; train into a new --run folder") from err
        if training_changes(changed):
            raise ValueError(
                f"{path}: the checkpoint was trained with other settings ({', '.join(changed)}); "
                "resume with the same settings, or train into a new --run folder"
            )
        self.model.gaussians = gaussians_of(ckpt["model"])
        self.model.load_state_dict(ckpt["model"])
        self.optimizers = gaussian_optimizers(self.model.gaussians, self.cfg.optim, self.extent)
        for k, o in self.optimizers.items():
            o.load_state_dict(ckpt["optimizers"][k])
        if self.field_opt is not None and ckpt["field_optimizer"] is not None:
            self.field_opt.load_state_dict(ckpt["field_optimizer"])
        self.step, self.train_seconds = ckpt["step"], ckpt["train_seconds"]
        self.model.set_static_mask(ckpt.get("static_mask"))
        if not changed:  # else calibrated again with the new settings when the steps are done
            self.extrapolation = load_extrapolation(self.run, self.device)
        if self.model.static_mask is not None:
            self.static_fraction = float(self.model.static_mask.float().mean())
        self.timings.update(ckpt.get("timings", {}))
        torch.set_rng_state(ckpt["rng"]["torch"].cpu())  # map_location moved it to the run's device
        random.setstate(ckpt["rng"]["python"])
