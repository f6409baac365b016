"""The sections of a training run's configuration (``TrainConfig`` nests them): ``optim``,
``densify``, ``stage2``. Each field's docstring is its ``--help``. The sections of the code below
the config package live beside it: ``deformation`` and ``dynamics`` in ``models/``, ``extrapolation``
in ``extrapolate/settings.py``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


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
    mask_weight: float = 0.0
    """Weight of the L1 between the coverage of the Gaussians that move (those not held static) and
    each training view's foreground mask, where there are masks and Gaussians held static
    (``stage2.static_outside_masks``): the subject's Gaussians draw the subject, and only it. 0 = off."""
    colour_lr: float = 1e-3
    """Learning rate of the per-camera gains (log) and offsets (``camera_colour``)."""
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
