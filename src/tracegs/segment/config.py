"""Settings of ``tracegs segment`` (every field is a flag: ``--settings.position-weight 0.5``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass
class SegmentConfig:
    """How the Gaussians of a trained run are grouped by their motion (docs/SEGMENTATION.md)."""

    features: Literal["physics", "flow"] = "physics"
    """``physics``: the paper's (|v_bar|, v_bar, |w|, w/|w|) from f_trd at the last training time;
    ``flow``: the baseline, f_defo's displacements over the training span (DefGS's scene flow)."""
    twist_neighbours: int = 24
    """The features' v_bar and w are the rigid motion that best explains the particle velocities
    (v_bar + w x x, from f_trd) of each Gaussian's this many nearest neighbours (0: each Gaussian's own
    f_trd output). A particle's velocity is well learned, its split into v_bar and w is not: alone, w
    is 0.4 on a wing turning at 0.93 and the features scatter over one part."""
    speed_weight: float = 1.0
    """Weight of |v_bar| (each feature group is normalised first, see ``normalise``)."""
    velocity_weight: float = 1.0
    """Weight of v_bar, the equivalent centre velocity (equal over a rigid part)."""
    spin_weight: float = 1.0
    """Weight of |w|, the angular speed."""
    axis_weight: float = 1.0
    """Weight of w/|w|, the rotation axis."""
    axis_floor: float = 0.1
    """The axis is w / max(|w|, axis_floor x the 90th percentile of |w| over the moving Gaussians): a
    part that only translates has no axis, and this keeps its noise out of the clustering."""
    position_weight: float = 0.0
    """Weight of the position at the last training time, a smoothness term as FreeGave uses (0: off)."""
    normalise: Literal["group", "none"] = "group"
    """``group``: each feature group is scaled to unit RMS over the moving Gaussians before its weight;
    ``none``: raw units."""
    static_displacement: float | None = None
    """Gaussians that f_defo moves less than this (scene units) over the training span form the static
    group; default: the run's freeze threshold (chosen on its training images), else
    ``stage2.static_displacement`` times the scene extent, as training marks them."""
    smooth_neighbours: int = 8
    """Labels are smoothed by a majority vote over this many nearest neighbours (0: off)."""
    piece_share: float = 0.25
    """A piece of a segment (connected by nearest neighbours) smaller than this share of it takes the
    label of what surrounds it: a part is one piece (0: off)."""
    refine_iterations: int = 3
    """Rounds in which each Gaussian joins the segment whose rigid motion (over the training span, and
    its twist at the feature time) best explains its own, averaged over its ``smooth_neighbours``
    nearest neighbours (0: off; the K-means labels as they are)."""
    starts: Literal["groups", "features"] = "groups"
    """The K-means partitions the refinement starts from, the one of lowest rigid cost kept: ``groups``,
    the weighted features and each feature group alone; ``features``, the weighted features only."""
    k_max: int = 8
    """Largest K that ``--auto-k`` tries (segments, the static group counted)."""
    rigid_tolerance: float = 0.02
    """``--auto-k`` stops at a K whose segments' velocities are this close to one rigid motion each
    (RMS residual over RMS speed)..."""
    rigid_gain: float = 0.5
    """... else at the smallest K that no larger K brings under this share of its residual."""
    flow_times: int = 8
    """Times over the training span at which f_defo's displacements are sampled (the flow features)."""
    seed: int = 0
    """Seed of K-means."""
