"""The settings of a ``TraceModel`` (``ModelConfig``): the method, its fields' sections, stage 2's
switches (``Stage2Config``), the SH degree, the rasteriser, per-camera colours and bf16. A training
run's ``TrainConfig`` holds them all and makes one (``TrainConfig.model_config``); its saved
``config.json`` keeps them where they always were."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from .deformation import DeformationConfig
from .dynamics import DynamicsConfig


@dataclass
class Stage2Config:
    """Stage 2 of TRACE (the paper's Section 3.3): f_defo and f_trd learn together; read by the
    model's training step (``TraceModel.training_state``) and by the trainer. The switches of the
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
    """Number of equal steps in which the sampled time range grows (eighths by default)."""
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
    static_outside_masks: bool = False
    """When stage 2 starts, mark static (as ``skip_static`` does) the Gaussians outside the region the
    foreground masks of the training times sweep, and not within ``static_margin`` spacings of it
    (``train/foreground.py``): the surroundings keep stage 1's fit, the fields see only the subject.
    Needs densification to have stopped (``densify.refine_stop`` <= ``static_iterations``)."""
    freeze_surroundings: bool = False
    """With ``static_outside_masks``: the Gaussians it holds static take no optimiser step in stage 2
    (their colours, opacities and shapes stay stage 1's fit, ``train/foreground.py``)."""
    views_per_step: int = 1
    """Cameras rendered per step at the step's time (a batch of views): the fields are evaluated once
    for that time and the loss is the mean over the views, so their cost is shared. Where fewer cameras
    saw the times (a monocular video: one), stage 2 runs as many more steps (the same number of views).
    1 = the paper's one-view step."""


@dataclass
class ModelConfig:
    """What a ``TraceModel`` is made of and how it draws (``TrainConfig.model_config``: the sections of
    a run's config, shared with it, not copied)."""

    method: Literal["trace", "defgs", "static"] = "trace"
    """trace = deformation + dynamics; defgs = deformation field alone; static = 3DGS at t = 0 only."""
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """f_defo, the auxiliary deformation field (none for ``static``, nor for ``trace`` without
    ``stage2.use_deformation``)."""
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    """f_trd, the translation-rotation dynamics field (trace only)."""
    stage2: Stage2Config = field(default_factory=Stage2Config)
    """How stage 2 trains the fields (``TraceModel.training_state``) and the integrator it runs."""
    sh_degree: int = 3
    """The spherical-harmonics degree of the trained colours (the one every image is drawn with)."""
    backend: str = "auto"
    """Rasteriser backend: auto, native, reference or gsplat."""
    camera_colour: bool = False
    """A gain and an offset per colour channel for each training camera (``models/colour.py``)."""
    bf16: bool = False
    """The fields under bf16 autocast on the CPU (``run.fields_in_bf16`` keeps it only on CPUs that
    multiply bf16 in hardware)."""
