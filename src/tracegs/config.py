"""Typed configuration of a training run, and the named presets.

Every constant of the method is a field here (or in the field configs it nests), with a docstring
that tyro turns into ``--help``. A run folder holds the resolved config as ``config.json``, read back
with :func:`load_config` (plain JSON into dataclasses, never ``eval``).
"""

from __future__ import annotations

import copy
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from .models.deformation import DeformationConfig
from .models.dynamics import DynamicsConfig
from .train.strategy import DensifyConfig


@dataclass
class OptimConfig:
    """Learning rates (3DGS for the Gaussians, Deformable-3DGS for the fields) and the loss."""

    means_lr: float = 1.6e-4
    """Initial position learning rate, multiplied by the scene extent."""
    means_lr_final: float = 1.6e-6
    """Final position learning rate (exponential decay), multiplied by the scene extent."""
    sh0_lr: float = 2.5e-3
    """Learning rate of the degree-0 SH coefficients."""
    shN_lr: float = 2.5e-3 / 20
    """Learning rate of the higher SH coefficients."""
    opacity_lr: float = 5e-2
    """Learning rate of the opacity logits."""
    scale_lr: float = 5e-3
    """Learning rate of the log-scales."""
    quat_lr: float = 1e-3
    """Learning rate of the quaternions."""
    field_lr: float = 8e-4
    """Initial learning rate of the deformation and dynamics fields (one Adam for both)."""
    field_lr_final: float = 1.6e-6
    """Final learning rate of the fields (exponential decay over the dynamic stage)."""
    grid_lr: float = 1.6e-3
    """Initial learning rate of the HexPlane planes (TRACE_4dgs), multiplied by the scene extent (4DGS)."""
    grid_lr_final: float = 1.6e-4
    """Final learning rate of the HexPlane planes, multiplied by the scene extent (4DGS)."""
    ssim_weight: float = 0.2
    """Loss = (1 - w) * L1 + w * (1 - SSIM)."""


@dataclass
class DynamicStageConfig:
    """Stage 2 of TRACE (METHOD.md "Training") and the ablation switches of the paper's Table 4."""

    dt_frames: float = 2.0
    """Delta t between t' and t in frame intervals (Table 4 row (1): 1, 2 or 3)."""
    integrator: Literal["rk2", "rk2_paper", "euler", "rk4"] = "rk2"
    """Integrator of the translation-rotation dynamics (rk2 = midpoint as the authors' code)."""
    use_deformation: bool = True
    """Ablation (3): without f_defo the dynamics start from the canonical Gaussians at t = 0."""
    physics_derivation: bool = True
    """Ablation (4): when false, f_trd is queried at the target time and its velocities used directly."""
    straight_through: bool = True
    """Render the physics position with f_defo's gradient passed straight through (x_phys + dx - dx.detach())."""
    straight_through_time: Literal["t_prime", "t"] = "t_prime"
    """Which displacement passes its gradient straight through: f_defo(t'), the start of the integration
    (METHOD.md; the physics then starts from a detached x_t'), or f_defo(t), the rendered time (one
    more field evaluation per step)."""
    time_growth_fraction: float = 0.19
    """The sampled time range grows in ``time_growth_stages`` steps over this fraction of the dynamic
    stage (the paper: ~7000 of 37000 iterations). A fraction, so that the late times of a shortened
    run are not introduced when the field learning rate has already decayed."""
    time_growth_stages: int = 8
    """Number of equal steps in which the sampled time range grows (METHOD.md: eighths). Each step
    opens times that f_defo has to reach from the motion it learned before them."""
    acceleration_consistency: float = 0.0
    """Weight of a loss that teaches f_trd's accelerations the time derivative of its own velocity
    field: f_trd is queried again at (x_t, t) and its velocities compared with those the accelerations
    predict from (x_t', t') (``physics.integrate.acceleration_consistency``). 0 = off (the paper). Over
    a two-frame transport an acceleration moves a point by a few hundredths of a pixel, too little for
    the photometric loss alone to learn it (docs/PHYSICS.md)."""
    consistency_frames: float = 0.0
    """Frame intervals between f_trd's query at t' and the later query that ``acceleration_consistency``
    compares its velocities with (0 = the step's own t - t'). The target is a finite difference of a
    fitted velocity field, whose small errors (0.01 in speed) over a two-frame baseline are errors of
    0.3 in acceleration; a longer baseline divides them. Same direction as t - t', turned back where it
    would leave the time range sampled so far (docs/PHYSICS.md)."""
    consistency_transport: Literal["dynamics", "deformation"] = "dynamics"
    """Where ``acceleration_consistency`` reads the later velocities: at the positions the step's own
    f_trd parameters carry x_t' to (``dynamics``), or at the same Gaussians moved to that time by
    f_defo (``deformation``: one more f_defo pass per step, without gradient). The first reads the
    velocity field at the wrong particles wherever the accelerations being learned are wrong; on a
    spinning body the velocity differs across it, so the target errs with them. Off in every preset:
    on the five validation futures it sums to -0.08 dB, `fan` -0.92 (docs/PHYSICS.md).
    Without f_defo (``use_deformation = False``) the transport is ``dynamics``."""
    angular_acceleration_penalty: float = 0.0
    """Weight of the mean |eps| of f_trd's angular accelerations (per component; a rotation rate, the
    same in the fields' frame and the world's), added to the step's loss: an L1 prior towards no
    angular acceleration. Below ``acceleration_consistency``'s weight it leaves an angular acceleration
    that the velocity field asks for consistently where it is and pulls the inconsistent ones to zero.
    Written against the spurious angular accelerations of a fan's blades and not measured (those came
    from a consistent drift; docs/PHYSICS.md). 0 = off."""
    rotation_consistency: float = 0.0
    """Weight of a loss that pulls each particle's angular velocity w towards the rotation of the rigid
    motion that best fits its neighbours' velocities (``physics.integrate.rotation_consistency``): a
    particle's velocity v_bar + w x x is rendered the same whether a translation or its body's rotation
    makes it, but only the rotation is consistent across the neighbourhood. 0 = off (the paper)."""
    rotation_neighbours: int = 8
    """Neighbours per Gaussian for ``rotation_consistency`` (found in the canonical space, refreshed as
    the set of Gaussians changes)."""
    hold_gaussians_steps: int = 0
    """For this many steps at the start of the dynamic stage the optimiser leaves the Gaussians' values
    as stage 1 left them and only the fields learn (densification goes on; 0 = off, the paper): the
    fields first learn the motion of the first time window, before the photometric loss can blur a
    moving part's appearance over the times f_defo does not yet follow."""
    warmup_deformation_steps: int = 0
    """Dynamic steps rendered with f_defo alone before the physics path is switched on."""
    handover_frames: float = 4.0
    """Frames before t_max from which the physics takes over from f_defo when rendering later times
    (the released code starts at 0.65-0.7 for data ending at 0.75; 0 = exactly t_max)."""
    extrapolation_requery: bool = False
    """Re-query f_trd at every step when extrapolating (Alg. 1 applied progressively); default: query once at
    the handover time and let the constant accelerations evolve the parameters (measured better on fan)."""
    hold_unseen: float = 10.0
    """After the handover, keep where they are the Gaussians that no training image shows over the last
    frames before it (found after training, ``train/calibrate.py``) and that f_trd moves more than
    this many times faster than f_defo moved them over the 4 frames before it (plus a floor of 0.05
    scene units per unit of time). Training shapes f_trd only through rendered images, so there its
    velocity is whatever the field's smoothness gives, and the physics would slide such a Gaussian
    (under a surface) into view; unseen Gaussians that f_trd moves as f_defo did (inside a moving
    object) move on. Not in the paper; 0 = off. Render time only (docs/PHYSICS.md)."""
    stay_on_surface: float = 0.5
    """After the handover, stop a moving Gaussian amid still ones (at least this fraction of its
    ``surface_neighbours`` nearest Gaussians frozen, marked static or held) where its path leaves the
    still surface around it: farther from every still Gaussian than twice its distance at the handover
    (or twice their typical spacing). Such Gaussians draw something that moves across a still surface
    (the shadow a moving part casts onto it), and while the physics carries them along the surface they
    may go on drawing it; off it they would smear it over the background (`fan`; docs/PHYSICS.md).
    Not in the paper; 0 = off. Render time only."""
    surface_neighbours: int = 16
    """Nearest Gaussians (at the handover) that ``stay_on_surface`` counts."""
    free_bodies: bool = False
    """After training, find the parts that move as one rigid body (without labels) and give each part
    that is free the future of a free body, a pivot on a parabola and a constant spin
    (``physics/free_body.py``): a part is free when it touches nothing still (``free_body_isolation``)
    and its free body, started ``free_body_backtest`` frames before the handover, predicts the training
    images up to t_max with less than ``free_body_tolerance`` times the learned physics' error (a group
    in flight whose parts turn on hinges is split into its rigid parts first, each tested alone). The
    learned physics cannot hold a spinning body that falls (docs/PHYSICS.md, "A free body per part").
    Not in the paper; off = the paper's extrapolation. Render time only."""
    free_body_window: int = 12
    """Frames of f_defo's path before the handover (or the backtest's start) that a free body's
    parabola is fitted to."""
    free_body_backtest: int = 8
    """Frames before the handover from which ``free_bodies`` backtests both models on the training
    images (up to t_max)."""
    free_body_refine_steps: int = 150
    """Adam steps that fit each free body (velocity, acceleration, spin, and where it is at the
    handover; the pivot stays at its centre of mass) to the training images of its window, from the
    parabola fitted to f_defo's path and f_trd's spin (``train/calibrate.py``, ``refine_free_body``);
    the backtest's body to the images before its start only. 0 = off."""
    free_body_refine_views: int = 8
    """Random training views rendered at each of those steps."""
    free_body_isolation: float = 20.0
    """A part is free only if 95% of its Gaussians lie farther than this many Gaussian spacings (the
    median nearest-neighbour distance) from every still Gaussian at the handover: a part on a hinge or
    a rail touches what holds it."""
    free_body_tolerance: float = 1.25
    """A free part's free body is kept while its backtest error (mean squared, on the training images)
    stays under this multiple of the learned physics'. Over a few frames the learned physics is about
    as good as a free body even where its accelerations are wrong (its error grows as the square of
    the time), so the backtest is a guard against a wrong free body, not a contest."""
    freeze_static_threshold: float = 0.0
    """Gaussians whose deformation stays below this displacement (scene units) are frozen when
    extrapolating (0 = off). Used when ``freeze_static_auto`` is off."""
    freeze_static_auto: bool = True
    """After training, choose the freeze threshold on the training images (pseudo-extrapolation over
    the last training frames, ``train/calibrate.py``); stored in the checkpoint."""
    skip_static: float = 0.0
    """Once densification has stopped and the sampled time range covers the training span, mark the
    Gaussians whose f_defo displacement over that span stays below this fraction of the scene extent
    as static: from then on they keep their canonical geometry at every time and f_defo and f_trd are
    evaluated on the moving Gaussians only (the fields' cost is proportional to the points they see,
    and most of a scene usually stands still). 0 = off (the paper). Needs f_defo; not combinable with
    ``rotation_consistency``, whose neighbourhoods span static and moving Gaussians."""


@dataclass
class TrainConfig:
    """A TRACE (or DefGS baseline) training run."""

    data: Path = Path("data/scene")
    """Scene folder in Blender/D-NeRF format (transforms_train.json, ...)."""
    run: Path = Path("runs/scene")
    """Output folder: checkpoints, config, logs, renders."""
    method: Literal["trace", "defgs", "static"] = "trace"
    """trace = deformation + dynamics; defgs = deformation field alone; static = 3DGS at t = 0 only."""
    preset: str = "paper"
    """Name of the preset this config was built from (recorded for reports)."""
    device: str = "auto"
    """'auto' (CUDA if present, else CPU), 'cpu' or 'cuda[:i]'."""
    seed: int = 0
    """Random seed."""
    downscale: int = 1
    """Integer factor by which images are downscaled when loaded."""
    t_train_end: float | None = None
    """Only training frames with time <= this are used (None: the dataset's value, else all)."""
    static_iterations: int = 3000
    """Stage 1: static 3DGS on the frames at t = 0."""
    dynamic_iterations: int = 37000
    """Stage 2: deformation + dynamics on all training frames (the paper runs 40k in total)."""
    init_points: int = 100_000
    """Random initial Gaussians in the scene bounds (when the dataset has no points)."""
    init_extent: float = 1.3
    """Half-size of the random-init cube when the dataset gives no aabb, for cameras 4.03 units from
    the point they look at (the Blender / D-NeRF layout); scaled with that distance (``init_box``)."""
    init_box: Literal["cameras", "origin"] = "cameras"
    """Where the random-init cube lies when the dataset gives no aabb or points: ``cameras`` centres
    it on the point the cameras look at and scales it with their distance (any capture's scale);
    ``origin``: +/- ``init_extent`` around the origin. Forward-facing captures fall back to ``origin``."""
    field_frame: Literal["auto", "cameras", "world"] = "auto"
    """The frame the fields see positions in (``train/scene_frame.py``, ``field_frame``): ``world``
    coordinates (the paper's), or the ``cameras``' frame (centred where they look, scaled by their
    distance against the Blender layout's 4.03) for a capture in any units; ``auto`` takes the world's
    when the scene already lies within a few units of the origin, else the cameras'."""
    sh_degree: int = 3
    """Maximum spherical-harmonics degree."""
    sh_degree_interval: int = 1000
    """Raise the active SH degree by one every this many steps."""
    bf16: bool = False
    """Run the fields under bfloat16 autocast on CPU (helps on CPUs with AMX). Training follows it;
    rendering and evaluation use it only on a CPU with AMX (elsewhere fp32 is faster and exact).
    Ignored on CUDA."""
    random_background: bool = False
    """Composite RGBA training images on a random colour each step (discourages floaters that
    imitate the background); images without alpha are unaffected."""
    backend: str = "auto"
    """Rasteriser backend: auto, native, reference or gsplat."""
    checkpoint_every: int = 2000
    """Write a checkpoint every this many steps (and at the end); a killed run resumes from it."""
    log_every: int = 100
    """Log losses and timings every this many steps."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    dynamic: DynamicStageConfig = field(default_factory=DynamicStageConfig)

    @property
    def total_iterations(self) -> int:
        return self.static_iterations + (0 if self.method == "static" else self.dynamic_iterations)


def paper() -> TrainConfig:
    """The paper's sizes: 8 x 256 fields, 3k static + 37k dynamic iterations, SH degree 3."""
    return TrainConfig(preset="paper")


def cpu_has_amx_bf16() -> bool:
    """True on x86 CPUs with AMX-BF16 tiles (there bf16 autocast makes the field MLPs ~1.5-3x faster)."""
    try:
        with open("/proc/cpuinfo") as f:
            return any("amx_bf16" in line for line in f if line.startswith("flags"))
    except OSError:
        return False


def cpu_fast() -> TrainConfig:
    """Tuned for 2 CPU cores at ~128 px: light fields, bf16 where it helps, a Gaussian budget."""
    cfg = TrainConfig(
        preset="cpu-fast",
        static_iterations=1500,
        # 20k rather than 12k dynamic steps since static skipping made steps cheaper: validation future
        # +0.55 / +0.64 / -0.13 dB on fan / foldingchair / fallingball, ~11 min on 2 cores (docs/DESIGN.md)
        dynamic_iterations=20000,
        bf16=cpu_has_amx_bf16(),
        random_background=True,
        init_points=5000,
        sh_degree=1,
        sh_degree_interval=500,
        checkpoint_every=1000,
        # the small fields keep learning late in the run: their learning rate decays 50x instead of
        # the paper's 500x; validation future +0.18 / +0.15 / +0.56 dB on fan / foldingchair /
        # fallingball at the same cost (docs/DESIGN.md)
        optim=OptimConfig(field_lr_final=1.6e-5),
        densify=DensifyConfig(
            refine_start=300, refine_stop=4500, refine_every=100, reset_every=3000, max_gaussians=7_000
        ),
        deformation=DeformationConfig(depth=4, width=64, skip_layer=2),
        # f_trd: L = 6 spatial frequencies (METHOD.md) and the acceleration consistency make the slider's
        # accelerating carriage learnable; three time frequencies: +2.6 dB on `bouncingballs`, within
        # 0.9 dB elsewhere, learned rotations and accelerations closer to the truth (docs/PHYSICS.md).
        # The accelerations from an MLP of their own (2 x 64 on the same encoding): they can follow
        # time where the shared features cannot; validation future +2.25 / +0.84 / +0.11 / -0.53 / -0.72 dB
        # on fallingball / fan / foldingchair / slider / satellite (docs/PHYSICS.md, "The accelerations
        # from their own MLP"). The angular ones from the shared head (features' gradient stopped): the
        # own MLP followed the fitted spin's end-of-span drift; fan +0.36 dB over the test split's
        # horizon, foldingchair 33.19 against 32.62 (docs/PHYSICS.md, "The angular rates from the head")
        dynamics=DynamicsConfig(
            depth=4,
            width=64,
            num_frequencies=6,
            time_frequencies=3,
            acceleration_depth=2,
            angular_accelerations_from_head=True,
            detach_acceleration_features=True,
        ),
        # the fields skip the Gaussians that have not moved by the end of densification: 25-33% less
        # time per step where half to three quarters of a scene stands still (docs/DESIGN.md).
        # The consistency target over 8 frames rather than the step's 2: the velocity field's slope is
        # least reliable at the span's end; validation future +0.91 / +0.14 dB on slider / fallingball
        # (docs/PHYSICS.md, "The consistency target over 8 frames").
        # Free bodies for the parts in flight (after training, render time only): validation future
        # +4.50 / +4.67 dB on two trainings of fallingball, the other four scenes unchanged on both;
        # fitted to the training images about the body's centre of mass, +1.5 dB more (docs/PHYSICS.md,
        # "A free body per part")
        dynamic=DynamicStageConfig(
            acceleration_consistency=0.01, consistency_frames=8.0, skip_static=0.003, free_bodies=True
        ),
    )
    return cfg


def tiny() -> TrainConfig:
    """A few iterations of everything: for tests and smoke runs."""
    cfg = cpu_fast()
    cfg.preset = "tiny"
    cfg.static_iterations, cfg.dynamic_iterations = 2, 2
    cfg.init_points = 200
    cfg.densify = DensifyConfig(refine_start=0, refine_every=1, reset_every=0)
    return cfg


PRESETS = {"paper": paper, "cpu-fast": cpu_fast, "tiny": tiny}


def make_config(preset: str = "cpu-fast", **overrides) -> TrainConfig:
    """A preset's config with top-level fields replaced by ``overrides``."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    return dataclasses.replace(PRESETS[preset](), **overrides)


def config_to_dict(cfg) -> dict:
    def convert(v):
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, dict):
            return {k: convert(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [convert(x) for x in v]
        return v

    return convert(dataclasses.asdict(cfg))


def config_from_dict(cls, data: dict):
    """Rebuild a (nested) config dataclass from plain JSON data; unknown keys are an error."""
    import typing

    hints = typing.get_type_hints(cls)
    kwargs = {}
    names = {f.name for f in dataclasses.fields(cls)}
    for key, value in data.items():
        if key not in names:
            raise ValueError(f"unknown config field {cls.__name__}.{key}")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            value = config_from_dict(hint, value)
        elif hint is Path:
            value = Path(value)
        elif isinstance(value, list) and "tuple" in str(hint).lower():
            value = _as_tuple(value)
        kwargs[key] = value
    return cls(**kwargs)


def _as_tuple(value):
    return tuple(_as_tuple(v) for v in value) if isinstance(value, list) else value


def save_config(cfg: TrainConfig, path: Path) -> None:
    from .utils import atomic_write_text

    atomic_write_text(path, json.dumps(config_to_dict(cfg), indent=2))


def load_config(path: Path) -> TrainConfig:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no config.json here (is this a tracegs run folder?)")
    return config_from_dict(TrainConfig, json.loads(path.read_text()))


def apply_overrides(cfg: TrainConfig, overrides: dict) -> TrainConfig:
    """A copy of ``cfg`` with fields set by name; nested fields as ``"dynamic__dt_frames"`` (section,
    double underscore, field)."""
    cfg = copy.deepcopy(cfg)
    for key, value in overrides.items():
        section, _, name = key.rpartition("__")
        target = getattr(cfg, section) if section else cfg
        if not hasattr(target, name):
            raise ValueError(f"unknown config field {key!r}")
        setattr(target, name, value)
    return cfg
