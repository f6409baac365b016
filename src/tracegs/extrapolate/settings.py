"""The settings of the policy after training (``TrainConfig.extrapolation``): read after the last step
and when rendering, never in training. Each field's docstring is its ``--help``."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


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
    (``extrapolate/calibrate.py``); the paper lets what never moved be frozen."""
    hold_unseen: bool = True
    """Hold still the Gaussians that no training image shows over the last frames before the handover
    and that f_trd moves more than ``unseen_speed_ratio`` times faster than f_defo moved them: f_trd
    was never shown them, and would slide them (from under a surface) into view. Not in the paper."""
    unseen_speed_ratio: float = 10.0
    """How much faster than f_defo (plus a floor of 0.05 scene units per unit of time) f_trd must move
    an unseen Gaussian for ``hold_unseen`` to hold it."""
    hold_surface: bool = True
    """Keep a moving Gaussian amid still ones (a surface painter) on its still surface after the
    handover, as ``surface_painters`` says: such Gaussians draw what moves across a still surface (a
    moving part's shadow), and off the surface would smear it over the background. Not in the paper."""
    surface_painters: Literal["edge", "hold"] = "edge"
    """What ``hold_surface`` does with a painter from the handover on: ``edge``: the physics carries it,
    and it stops for good at the first step that would take it off its surface (farther from every
    still Gaussian than twice its distance at the handover, or twice their spacing); ``hold``: it
    holds still at its state there (a shadow stops moving, but cannot slide across its surface and
    past its rim, as f_trd sometimes carries it; docs/PHYSICS.md)."""
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
    are, among the moving Gaussians, and not a free body) an identified model of its joint coordinate,
    ``q'' = f(q, q')`` (``physics/identify.py``: a sparse sum of library terms, split at velocity
    jumps), identified on f_defo's path of the part up to the handover and integrated on from there
    (``extrapolate/joints.py``). A model is adopted only where it is more than a constant acceleration,
    is stable, predicts the held-out end of that path clearly better than moving on at the last
    velocity, fits the whole path, and predicts the part's positions there no worse than
    ``joint_law_tolerance`` times the learned physics does; elsewhere the learned physics stays (the
    paper's extrapolation) and the run summary says why. A part that turns on a joint of its own on
    such a part (a box spinning on a turntable) is put on that joint in the carrier's frame, and a
    moving group that bounces on a floor within the span falls under gravity with a contact
    (``extrapolate/thrown.py``), each under the same backtest. Off = the paper's extrapolation
    (``paper``); on in ``cpu-fast`` and ``capture``."""
    joint_law_holdout: float = 0.25
    """Fraction of the part's frames at the end of its path up to the handover (at least one) that the
    model is fitted without and scored on, to choose its terms and to backtest it against the learned
    physics; the chosen terms are then fitted to every frame."""
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
