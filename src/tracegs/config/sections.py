"""The sections of a training run's configuration (``TrainConfig`` nests them) that have no home
beside their code: ``optim`` and ``densify``. Each field's docstring is its ``--help``. The model's
sections (``deformation``, ``dynamics``, ``stage2``) live in ``models/``, ``extrapolation`` in
``extrapolate/settings.py``.

``OptimConfig`` and ``DensifyConfig`` configure ``train/`` (the optimisers, the densification
strategy), a layer above this package: defined there, ``config`` would import ``train``, which
imports ``config`` for ``TrainConfig``, a cycle. They stay here, where ``train/`` imports them from."""

from __future__ import annotations

from dataclasses import dataclass


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
    moving_refine_stop: int = 0
    """Step of the run until which stage 2 densifies the Gaussians that move (those not held static by
    ``stage2.static_outside_masks`` or ``skip_static``; all, where none is held): clone, split, prune
    and opacity resets on the schedule above, the held ones untouched, so that what moves gets
    Gaussians where the images of later times need them. 0 = off (stage 2 trains the Gaussians of
    stage 1)."""
    moving_max_gaussians: int = 20_000
    """Stage 2's densification grows the moving Gaussians up to this count."""
    refine_stop_fraction: float = 0.5
    """Densification and opacity resets also stop after this fraction of the run's iterations, so that a
    shortened run (e.g. ``--dynamic-iterations 2000``) still ends with a phase of plain optimisation."""
