"""Typed configuration of a training run, and the named presets.

Every constant of the method is a field here (or in the field configs it nests), with a docstring
that tyro turns into ``--help``. Sections: ``optim`` (learning rates, loss), ``densify`` (adaptive
density control), ``deformation`` (f_defo), ``dynamics`` (f_trd), ``stage2`` (how stage 2 trains the
fields, with the paper's Table 4 switches) and ``extrapolation`` (what happens after training: the
handover, what holds still, free bodies; read after the last step and when rendering, never in
training). Why each preset value is what it is: docs/DESIGN.md; the numbers behind it: docs/RESULTS.md.
A run folder holds the resolved config as ``config.json`` (``run.py``; plain JSON, never ``eval``).
``validate(cfg)`` (``config/validate.py``) checks every setting before anything is trained.
"""

from __future__ import annotations

import copy
import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ..models.deformation import DeformationConfig
from ..models.dynamics import DynamicsConfig
from ..utils import cpu_has_amx_bf16
from .validate import check_setting, flag_name, validate  # noqa: F401  (part of the config API)


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
    nan_lr_factor: float = 0.5
    """What every learning rate is multiplied by when a non-finite loss, gradient or parameter makes
    training restore its last good state (once; the second time training stops)."""


@dataclass
class DensifyConfig:
    """Adaptive density control (clone / split / prune / opacity reset), 3DGS defaults."""

    refine_start: int = 500
    """Step (within the stage) at which densification starts."""
    refine_stop: int = 15_000
    """Step after which the number of Gaussians is frozen."""
    refine_every: int = 100
    """Densify and prune every this many steps."""
    reset_every: int = 3000
    """Reset opacities to ``reset_opacity`` every this many steps (0 = never)."""
    reset_opacity: float = 0.01
    """Opacity after a reset (3DGS: 0.01)."""
    grow_grad2d: float = 0.0002
    """View-space (NDC) positional gradient above which a Gaussian is cloned or split."""
    grow_scale3d: float = 0.01
    """Relative to the scene extent: smaller Gaussians are cloned, larger ones split."""
    prune_opacity: float = 0.005
    """Gaussians below this opacity are removed."""
    prune_scale3d: float = 0.1
    """Relative to the scene extent: larger Gaussians are removed (after the first opacity reset)."""
    max_gaussians: int = 1_000_000
    """Growth stops at this count (a budget for slow devices)."""
    refine_stop_fraction: float = 0.5
    """Densification and opacity resets also stop after this fraction of the run's iterations, so that a
    shortened run (e.g. ``--dynamic-iterations 2000``) still ends with a phase of plain optimisation."""


@dataclass
class Stage2Config:
    """Stage 2 of TRACE (METHOD.md "Training"): f_defo and f_trd learn together; the switches of the
    paper's Table 4 are ``dt_frames``, ``use_deformation``, ``physics_derivation`` (with
    ``dynamics.order`` and ``dynamics.equivalent``)."""

    dt_frames: float = 2.0
    """Delta t between t' and t in frame intervals (Table 4 row (1): 1, 2 or 3)."""
    integrator: Literal["rk2", "rk2_paper", "euler", "rk4"] = "rk2"
    """Integrator of the translation-rotation dynamics, in training and extrapolation (rk2 = midpoint,
    as the authors' code)."""
    use_deformation: bool = True
    """Ablation (3): without f_defo the dynamics start from the canonical Gaussians at t = 0."""
    physics_derivation: bool = True
    """Ablation (4): when false, f_trd is queried at the target time and its velocities used directly
    (and re-queried at every step when extrapolating)."""
    time_growth_fraction: float = 0.19
    """The sampled time range grows in ``time_growth_stages`` steps over this fraction of the stage (the
    paper: ~7000 of 37000 iterations); a fraction, so that a shortened run grows as fast."""
    time_growth_stages: int = 8
    """Number of equal steps in which the sampled time range grows (METHOD.md: eighths)."""
    acceleration_consistency: float = 0.0
    """Weight of a loss that teaches f_trd's accelerations the time derivative of its own velocity
    field: f_trd is queried again where x_t' is carried to and its velocities compared with those the
    accelerations predict (``physics.integrate.acceleration_consistency``). 0 = off (the paper)."""
    consistency_frames: float = 0.0
    """Frame intervals between f_trd's query at t' and the later query that ``acceleration_consistency``
    compares with (0 = the step's own t - t'); same direction as t - t', turned back where it would
    leave the time range sampled so far. A longer baseline divides the finite difference's error."""
    skip_static: bool = False
    """Once densification has stopped and the sampled time range covers the training span, mark the
    Gaussians that f_defo moves less than ``static_displacement`` as static: from then on they keep
    their canonical geometry at every time and the fields are evaluated on the moving ones only (the
    fields' cost is proportional to the points they see). Off in the paper. Needs f_defo."""
    static_displacement: float = 0.003
    """Largest f_defo displacement over the training span, as a fraction of the scene extent, of a
    Gaussian that ``skip_static`` marks static."""
    static_margin: float = 5.0
    """``skip_static`` leaves moving the Gaussians within this many median neighbour spacings of one
    that moves: a part's slow patch by its hinge turns with it instead of being frozen (0: none)."""
    views_per_step: int = 1
    """Cameras rendered per step at the step's time (a batch of views): the fields are evaluated once
    for that time and the loss is the mean over the views, so their cost is shared. Where fewer cameras
    saw the times (a monocular video: one), stage 2 runs as many more steps (the same number of views).
    1 = the paper's one-view step."""


@dataclass
class ExtrapolationConfig:
    """After training: from which time the learned physics renders, which Gaussians it leaves still,
    and which parts move as free bodies (``tracegs/extrapolate``, docs/PHYSICS.md "Extrapolation").
    Chosen on the training images only, once, when training ends (``tracegs calibrate`` again)."""

    handover_frames: float = 4.0
    """Frames before t_max from which the physics takes over from f_defo when rendering later times
    (the released code starts at 0.65-0.7 for data ending at 0.75; 0 = exactly t_max)."""
    freeze_static: bool = True
    """Hold still the Gaussians whose f_defo displacement over the training span stays below a
    threshold, chosen after training by a pseudo-extrapolation on the training images
    (``extrapolate/calibrate.py``); METHOD.md allows freezing what never moved."""
    hold_unseen: bool = True
    """Hold still the Gaussians that no training image shows over the last frames before the handover
    and that f_trd moves more than ``unseen_speed_ratio`` times faster than f_defo moved them: f_trd
    was never shown them, and would slide them (from under a surface) into view. Not in the paper."""
    unseen_speed_ratio: float = 10.0
    """How much faster than f_defo (plus a floor of 0.05 scene units per unit of time) f_trd must move
    an unseen Gaussian for ``hold_unseen`` to hold it."""
    hold_surface: bool = True
    """Stop a moving Gaussian amid still ones where its path leaves the still surface around it
    (farther from every still Gaussian than twice its distance at the handover, or twice their
    spacing): such Gaussians draw what moves across a still surface (a moving part's shadow), and off
    the surface would smear it over the background. Not in the paper."""
    surface_still_fraction: float = 0.5
    """Fraction of its ``surface_neighbours`` nearest Gaussians that must hold still for
    ``hold_surface`` to count a moving Gaussian as drawing on their surface."""
    surface_neighbours: int = 16
    """Nearest Gaussians (at the handover) that ``hold_surface`` counts."""
    free_bodies: bool = False
    """Find the parts that move as one rigid body (without labels) and give each free part the future
    of a free body, a pivot on a parabola and a constant spin (``physics/free_body.py``): free when it
    touches nothing still (``free_body_isolation``) and its free body, started ``free_body_backtest``
    frames before the handover, predicts the training images up to t_max with less than
    ``free_body_tolerance`` times the learned physics' error. Off = the paper's extrapolation."""
    free_body_window: int = 12
    """Frames of f_defo's path before the handover (or the backtest's start) that a free body's
    parabola is fitted to."""
    free_body_backtest: int = 8
    """Frames before the handover from which both models are backtested on the training images."""
    free_body_refine_steps: int = 150
    """Adam steps that fit each free body (velocity, acceleration, spin, position at the handover) to
    the training images of its window (``extrapolate/free_bodies.py``). 0 = off."""
    free_body_refine_views: int = 8
    """Random training views rendered at each of those steps."""
    free_body_isolation: float = 20.0
    """A part is free only if 95% of its Gaussians lie farther than this many Gaussian spacings (the
    median nearest-neighbour distance) from every still Gaussian at the handover."""
    free_body_tolerance: float = 1.25
    """A free part's free body is kept while its backtest error (mean squared, on the training images)
    stays under this multiple of the learned physics'."""
    joint_laws: bool = False
    """Give each rigid part that turns on a hinge or slides on a rail (found as the free bodies' parts
    are, among the moving Gaussians, and not a free body) a force law of its one joint coordinate,
    ``q'' = f(q, q')`` (``physics/force_law.py``: constant, friction stop, spring-damper, pendulum),
    identified on f_defo's path of the part up to the handover and integrated on from there
    (``extrapolate/joints.py``). A law is adopted only where it is not ``constant`` and predicts the
    held-out end of that path better than moving on at the last velocity and no worse than
    ``joint_law_tolerance`` times the learned physics does; elsewhere the learned physics stays (the
    paper's extrapolation) and the run summary says why. Off = the paper's extrapolation."""
    joint_law_holdout: float = 0.25
    """Fraction of the part's frames at the end of its path up to the handover (at least one) that the
    laws are fitted without and scored on, to choose among them (``choose_law``) and to backtest the
    chosen one against the learned physics; the chosen law is then fitted to every frame."""
    joint_law_tolerance: float = 0.8
    """A joint law is adopted only while its error on the held-out frames (RMS distance of the part's
    Gaussians from f_defo's) stays under this multiple of the learned physics' started at the same
    frame. Below 1: the learned physics is the paper's and holds a steady hinge by construction, so a
    law must beat it clearly (on a steady `fan` a law within 0.96x of it cost 0.03 dB)."""
    joint_fit_tolerance: float = 0.05
    """A part is put on a joint only when the better of its hinge and its slider reproduces f_defo's
    positions of the part over the frames within this fraction of the part's radius (RMS distance of
    its Gaussians from their mean at the handover) of what the part's best rigid motion per frame
    reproduces (RMS over its Gaussians and frames; f_defo moves no part exactly rigidly): what turns
    on no fixed axis and slides along no fixed line keeps the learned physics."""


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
    """The named preset whose values are the defaults of every other setting: paper, cpu-fast or tiny
    (``config.PRESETS``); recorded in the run folder."""
    device: str = "auto"
    """'auto' (CUDA if present, else CPU), 'cpu' or 'cuda[:i]'."""
    threads: int = 0
    """CPU threads of the training; 0: one per core that other processes leave free, counted at the
    start and every 30 s (``train/threads.py``; ``OMP_NUM_THREADS``, when set, is kept)."""
    seed: int = 0  # random seed
    downscale: int = 1  # integer factor by which images are downscaled when loaded
    t_train_end: float | None = None
    """Only training frames with time <= this are used (None: the dataset's value, else all)."""
    static_iterations: int = 3000
    """Stage 1: static 3DGS on the frames at t = 0."""
    dynamic_iterations: int = 37000
    """Stage 2: deformation + dynamics on all training frames (the paper runs 40k in total); steps of
    ``stage2.views_per_step`` views, more where fewer cameras saw each time."""
    init_points: int = 100_000
    """Random initial Gaussians in the scene bounds (when the dataset has no points)."""
    init_extent: float = 1.3
    """Half-size of the random-init cube when the dataset gives no aabb, for cameras 4.03 units from
    the point they look at (the Blender / D-NeRF layout); scaled with that distance (``init_box``)."""
    init_box: Literal["cameras", "origin"] = "cameras"
    """Where the random-init cube lies when the dataset gives no aabb or points: ``cameras`` centres
    it on the point the cameras look at and scales it with their distance (any capture's scale);
    ``origin``: +/- ``init_extent`` around the origin. Forward-facing captures fall back to ``origin``."""
    init_hull: bool = False
    """Add Gaussians on the visual hull of the first time's foreground masks, carved in that cube
    (``data/masks.py``, ``data/hull.py``; none without masks). ``hull_resolution``: voxels a side."""
    hull_resolution: int = 96
    field_frame: Literal["auto", "cameras", "world"] = "auto"
    """The frame the fields see positions in (``train/scene_frame.py``): ``world`` coordinates (the
    paper's), or the ``cameras``' frame (centred where they look, scaled by their distance against the
    Blender layout's 4.03) for a capture in any units; ``auto``: the world's when the scene already lies
    within a few units of the origin, else the cameras'."""
    sh_degree: int = 3  # maximum spherical-harmonics degree
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
    log_every: int = 100  # log losses and timings every this many steps
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """f_defo, the auxiliary deformation field."""
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    """f_trd, the translation-rotation dynamics field."""
    stage2: Stage2Config = field(default_factory=Stage2Config)
    extrapolation: ExtrapolationConfig = field(default_factory=ExtrapolationConfig)

    @property
    def total_iterations(self) -> int:
        return self.static_iterations + (0 if self.method == "static" else self.dynamic_iterations)


def paper() -> TrainConfig:
    """The paper's sizes: 8 x 256 fields, 3k static + 37k dynamic iterations, SH degree 3."""
    return TrainConfig(preset="paper")


def cpu_fast() -> TrainConfig:
    """Minutes on 2 CPU cores at ~128 px: small fields, bf16 where it helps, a Gaussian budget, fields
    that skip the Gaussians standing still, free bodies for the parts in flight (docs/DESIGN.md)."""
    return TrainConfig(
        preset="cpu-fast",
        static_iterations=1500,
        dynamic_iterations=20000,
        bf16=cpu_has_amx_bf16(),
        random_background=True,
        init_points=5000,
        sh_degree=1,
        sh_degree_interval=500,
        checkpoint_every=1000,
        optim=OptimConfig(field_lr_final=1.6e-5),
        densify=DensifyConfig(
            refine_start=300, refine_stop=4500, refine_every=100, reset_every=3000, max_gaussians=7_000
        ),
        deformation=DeformationConfig(depth=4, width=64, skip_layer=2),
        dynamics=DynamicsConfig(
            depth=4,
            width=64,
            num_frequencies=6,
            time_frequencies=3,
            acceleration_depth=2,
            angular_accelerations_from_head=True,
            detach_acceleration_features=True,
        ),
        stage2=Stage2Config(acceleration_consistency=0.01, consistency_frames=8.0, skip_static=True),
        extrapolation=ExtrapolationConfig(free_bodies=True),
    )


def tiny() -> TrainConfig:
    """A few iterations of everything: for tests and smoke runs."""
    cfg = cpu_fast()
    cfg.preset = "tiny"
    cfg.static_iterations, cfg.dynamic_iterations = 2, 2
    cfg.init_points = 200
    # densifying every step without a budget grows to 10^5 Gaussians on a real scene in a few steps
    cfg.densify = DensifyConfig(refine_start=0, refine_every=1, reset_every=0, max_gaussians=20_000)
    return cfg


PRESETS = {"paper": paper, "cpu-fast": cpu_fast, "tiny": tiny}
"""The named presets, each a function that builds its config (``--preset NAME``)."""


def make_config(preset: str = "cpu-fast", **overrides) -> TrainConfig:
    """A preset's config with fields set by name (``config.apply_overrides``: ``stage2.dt_frames``)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    return apply_overrides(PRESETS[preset](), overrides)


def config_to_dict(cfg) -> dict:
    """A config as plain JSON data (paths as strings)."""

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


def apply_overrides(cfg: TrainConfig, overrides: dict) -> TrainConfig:
    """A copy of ``cfg`` with fields set by their dotted names, as the command line spells them
    (``{"stage2.dt_frames": 3.0}`` for ``--stage2.dt-frames 3``); an unknown name is an error."""
    cfg = copy.deepcopy(cfg)
    for key, value in overrides.items():
        *sections, name = key.split(".")
        target = cfg
        for section in sections:
            target = getattr(target, section, None)
            if target is None or not dataclasses.is_dataclass(target):
                raise ValueError(f"unknown config section in {key!r}")
        if name not in {f.name for f in dataclasses.fields(target)}:
            raise ValueError(f"unknown config field {key!r}")
        setattr(target, name, value)
    return cfg
