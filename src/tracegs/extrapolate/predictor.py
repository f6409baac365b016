"""A trained run as one object: the model, its post-training state and its settings, which turn any
time t into Gaussians and any camera at t into an image.

Up to the handover (``handover_frames`` before t_max) f_defo places the Gaussians, as in training;
later the learned physics (f_trd, integrated from the handover) moves every Gaussian but those that
hold still (``still.py``: one code per Gaussian says which and why) and those that move as free bodies
(``free_bodies.py``) or with identified models (``joints.py``). The methods without f_trd (DefGS,
static 3DGS) render f_defo or the canonical Gaussians at every time.

``run.load_run`` builds the ``Predictor`` of a run folder and the trainer's last calibration builds
it when training ends (``calibrate.calibrate``); evaluation, export, the viewer, segmentation and the
calibration's own scoring all go through it, so "deform, then physics, then render" is composed here
only.
N: Gaussians, K: segments.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ..physics.free_body import apply_free_bodies
from ..physics.integrate import num_substeps, step
from ..physics.so3 import quat_multiply, quat_normalize, rotmat_to_quat
from .joint_motion import apply_joint_laws
from .settings import ExtrapolationConfig
from .state import ExtrapolationState
from .still import moving_after_handover
from .surface import SurfacePainters

MOTIONS = ("trace", "f_defo", "hold")
"""How a ``Predictor`` moves the Gaussians: ``trace`` (f_defo up to the handover, then the learned
physics and the chosen parts' models: what TRACE predicts), ``f_defo`` (the deformation field queried
at every time, past its training span too: what DefGS predicts) or ``hold`` (f_defo up to the training
span's end t_max, then f_defo's Gaussians at t_max held still: the baseline "nothing moves any more"
that a prediction must beat)."""

MAX_TIME_FACTOR = 10.0
"""Latest time a command renders, in multiples of the training span's end (and at least 1): the
extrapolation integrates the physics from the training span's end, so the cost grows with t."""

ALPHA_MIN = 0.5
"""Pixels less opaque than this are background in a label image (``render_labels``)."""


def check_time(t: float, t_max: float, flag: str = "--time") -> float:
    """``t`` when a run trained up to ``t_max`` can render it: finite, >= 0, and no later than
    ``MAX_TIME_FACTOR`` x ``t_max`` (at least 1); else a ValueError naming ``flag``."""
    limit = max(MAX_TIME_FACTOR * t_max, 1.0)
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"{flag} must be a finite time >= 0, got {t}")
    if t > limit:
        raise ValueError(
            f"{flag} {t:g} is beyond the limit {limit:g} ({MAX_TIME_FACTOR:g} x the training span's end "
            f"{t_max:g}): the extrapolation's cost grows with t"
        )
    return t


class Predictor:
    """A trained run: ``model`` (``models.TraceModel``), its post-training ``state`` and the
    ``settings`` of the policy after training, with the render ``background`` [3] (None: black)."""

    def __init__(
        self,
        model,
        state: ExtrapolationState,
        settings: ExtrapolationConfig | None = None,
        background: torch.Tensor | None = None,
    ):
        self.model = model
        self.state = state
        self.settings = ExtrapolationConfig() if settings is None else settings
        self.background = (
            None if background is None else torch.as_tensor(background, dtype=torch.float32).to(self.device)
        )

    # ----- what it is ---------------------------------------------------------------------------
    @property
    def device(self) -> torch.device:
        return self.model.aabb.device

    @property
    def t_max(self) -> float:
        """The end of the training span: later times are predicted."""
        return float(self.state.t_max)

    @property
    def sh_degree(self) -> int:
        return self.model.sh_degree

    def with_settings(self, **changes) -> Predictor:
        """The same run with some ``settings`` changed (those that change rendering without a new
        calibration, e.g. ``free_bodies=False``); the state is shared, its cache included."""
        settings = dataclasses.replace(self.settings, **changes)
        return Predictor(self.model, self.state, settings, self.background)

    def with_background(self, background) -> Predictor:
        """The same run rendered on ``background`` (RGB in [0, 1], e.g. the scene's)."""
        return Predictor(self.model, self.state, self.settings, background)

    def handover_time(self) -> float:
        """Last time rendered by f_defo alone; later times are integrated from it. f_defo is least
        constrained at the end of the training span, so (as the authors' code does) the physics takes
        over a few frames before the data ends."""
        return max(0.0, self.t_max - self.settings.handover_frames * self.model.dt_max)

    def check_time(self, t: float, flag: str = "--time") -> float:
        """``t`` when the run can render it (``check_time``); else a ValueError naming ``flag``."""
        return check_time(t, self.t_max, flag)

    def describe(self) -> dict:
        """What the run predicts with: its method, Gaussians, training span, handover and the parts
        that the policy gave their own motion (plain data, for reports and ``summary.json``)."""
        state, settings = self.state, self.settings
        bodies, joints = state.free_bodies, state.joint_laws
        return {
            "method": self.model.method,
            "gaussians": int(self.model.gaussians["means"].shape[0]),
            "t_max": self.t_max,
            "handover": self.handover_time() if self.model.dynamics is not None else None,
            "freeze_threshold": state.freeze_threshold,
            "unseen": None if state.unseen is None else int(state.unseen.sum()),
            "free_bodies": len(bodies["bodies"]) if settings.free_bodies and bodies is not None else 0,
            "joint_parts": len(joints["parts"]) if settings.joint_laws and joints is not None else 0,
        }

    # ----- the Gaussians at any time ------------------------------------------------------------
    @torch.no_grad()
    def gaussians_at(self, t: float, motion: str = "trace") -> dict[str, torch.Tensor]:
        """Geometry of the Gaussians at time ``t`` (``means`` [N, 3], ``quats`` [N, 4], log-``scales``
        [N, 3]) under ``motion`` (``MOTIONS``): for ``trace`` f_defo up to the handover, then the
        learned physics, the still Gaussians, the free bodies and the joint parts."""
        model, g = self.model, self.model.gaussians
        if motion == "f_defo":
            return model.deform(t)
        if motion == "hold":
            return model.deform(min(t, self.t_max))
        if motion != "trace":
            raise ValueError(f"motion {motion!r}: expected one of {list(MOTIONS)}")
        if model.method == "static":
            return {"means": g["means"], "quats": g["quats"], "scales": g["scales"]}
        if model.dynamics is None:
            return model.deform(t)
        if model.deformation is None:
            return self.physics_from(0.0, t)
        t0 = self.handover_time()
        if t <= t0:
            return model.deform(t)
        start = model.deform(t0)  # where the physics, the free bodies and the joint parts start from
        gaussians = self._with_free_bodies(t0, t, self.physics_from(t0, t, start=start), start)
        return self._with_joint_laws(t0, t, gaussians, start)

    @torch.no_grad()
    def gaussians_carried(self, t: float, labels: torch.Tensor, motions) -> dict[str, torch.Tensor]:
        """The Gaussians at ``t`` moved rigidly from f_defo's state at the handover, those of label ``k``
        [N] (> 0) by ``motions(t)[k - 1]`` ([B, 4, 4], from the handover to ``t``; a simulator's
        bodies, ``export/simulate.py``), the others held there; f_defo's before the handover."""
        t0 = self.handover_time()
        if t <= t0:
            return self.model.deform(t)
        start = self.model.deform(t0)
        means, quats = start["means"].clone(), quat_normalize(start["quats"]).clone()
        labels = labels.to(means.device)
        for k, motion in enumerate(torch.as_tensor(np.asarray(motions(t)), dtype=torch.float64)):
            rows = labels == k + 1
            if bool(rows.any()):
                turn, shift = motion[:3, :3].to(means.device), motion[:3, 3].to(means.device)
                means[rows] = (start["means"][rows].double() @ turn.T + shift).to(means.dtype)
                q = rotmat_to_quat(turn).to(quats.dtype)[None].expand(int(rows.sum()), 4)
                quats[rows] = quat_multiply(q, quats[rows])
        return {**start, "means": means, "quats": quats}

    @torch.no_grad()
    def parameters_at(self, t: float, motion: str = "trace") -> dict[str, torch.Tensor]:
        """Every parameter of the Gaussians at time ``t`` (what a splat file holds): the geometry of
        ``gaussians_at`` and the canonical opacities and colours."""
        g, geometry = self.model.gaussians, self.gaussians_at(t, motion)
        return {
            "means": geometry["means"], "quats": geometry["quats"], "scales": geometry["scales"],
            "opacities": g["opacities"], "sh0": g["sh0"], "shN": g["shN"],
        }  # fmt: skip

    def _with_free_bodies(self, t0: float, t: float, gaussians: dict, start: dict) -> dict:
        """``gaussians`` (the learned physics at ``t``) with the free bodies' Gaussians moved as free
        bodies from ``start``, f_defo's state at ``t0`` (``physics/free_body.py``)."""
        bodies = self.state.free_bodies
        if not self.settings.free_bodies or bodies is None or not len(bodies["bodies"]):
            return gaussians
        if not _chosen_here(bodies, t0, gaussians["means"].shape[0]):
            return gaussians
        labels = bodies["labels"].to(gaussians["means"].device)
        return apply_free_bodies(gaussians, start, labels, bodies["bodies"], t - t0)

    def _with_joint_laws(self, t0: float, t: float, gaussians: dict, start: dict) -> dict:
        """``gaussians`` with the joint parts' Gaussians moved by their identified models from ``start``,
        f_defo's state at ``t0`` (``joints.py``; ``joint_laws``)."""
        joints = self.state.joint_laws
        if not self.settings.joint_laws or joints is None or not joints["parts"]:
            return gaussians
        if not _chosen_here(joints, t0, gaussians["means"].shape[0]):
            return gaussians
        return apply_joint_laws(gaussians, start, joints, t)

    @torch.no_grad()
    def physics_from(
        self,
        t0: float,
        t: float,
        moving: torch.Tensor | None = None,
        start: dict[str, torch.Tensor] | None = None,
    ) -> dict[str, torch.Tensor]:
        """Deform to ``t0`` and chain integration steps of at most one frame interval to ``t`` (forward
        or back), leaving the Gaussians that hold still at their ``t0`` state.

        ``moving`` [N] bool: the Gaussians above the freeze threshold (default: from the state); the
        still codes of ``still.py`` then apply on top of it. With ``hold_surface`` a Gaussian that
        paints a still surface holds still (``surface_painters="hold"``) or stops at the first step
        that would take it off that surface (``"edge"``). ``start``: ``model.deform(t0)`` where the
        caller has it.
        """
        model, settings = self.model, self.settings
        gaussians = model.deform(t0) if start is None else start
        means, quats = gaussians["means"], quat_normalize(gaussians["quats"])
        params = model.query_dynamics(means, t0)
        moving = moving_after_handover(self, t0, means, params, moving)
        surface = None
        if settings.hold_surface and moving is not None and t > t0:
            surface = self._surface_painters(means, moving)
            if surface is not None and settings.surface_painters == "hold":
                moving = moving.clone()
                moving[surface.rows] = False  # held at their t0 state below
                surface = None
            stopped = torch.zeros_like(moving)  # painters stopped so far ("edge")
        span = t - t0
        n = num_substeps(span, model.dt_max) if span else 0
        h = span / max(n, 1)
        # f_trd is queried once, at t0, and its constant accelerations evolve the parameters between
        # steps (``integrate``); without the physics derivation (ablation (4)) it is queried at every
        # step's end.
        requery = not model.stage2.physics_derivation
        new_means, new_quats = means, quats
        for k in range(n):
            s = t0 + k * h
            if requery:
                params = model.query_dynamics(new_means, s + h)
            next_means, next_quats, evolved = step(new_means, new_quats, params, h, model.stage2.integrator)
            params = params if requery else evolved
            if surface is not None:  # stopped where they would leave their surface
                stopped[surface.rows] |= surface.off(next_means[surface.rows])
                next_means = torch.where(stopped[:, None], new_means, next_means)
                next_quats = torch.where(stopped[:, None], new_quats, next_quats)
            new_means, new_quats = next_means, next_quats
        if moving is not None:
            new_means = torch.where(moving[:, None], new_means, means)
            new_quats = torch.where(moving[:, None], new_quats, quats)
        return {"means": new_means, "quats": new_quats, "scales": gaussians["scales"]}

    def _surface_painters(self, means: torch.Tensor, moving: torch.Tensor) -> SurfacePainters | None:
        """The surface painters of this handover state (``SurfacePainters.find``), kept in the state's
        cache for the next call with the same state (every rendered time after the handover)."""
        key = (self.settings.surface_still_fraction, self.settings.surface_neighbours)
        cached = self.state.cache.get("surface")
        if (
            cached is not None
            and cached[3] == key
            and cached[0].device == means.device
            and torch.equal(cached[0], means)
            and torch.equal(cached[1], moving)
        ):
            return cached[2]
        painters = SurfacePainters.find(means, moving, *key)
        self.state.cache["surface"] = (means, moving, painters, key)
        return painters

    # ----- images ---------------------------------------------------------------------------------
    @torch.no_grad()
    def render(
        self, camera, t: float | None = None, gaussians: dict | None = None, camera_id: int | None = None
    ) -> torch.Tensor:
        """Image [H, W, 3] in [0, 1] seen by ``camera`` of the scene at time ``t`` (or of ``gaussians``,
        their geometry at some time, as ``gaussians_at`` gives it), in the colours of the training
        camera ``camera_id`` (``models/colour.py``; None: a camera the run was not trained with)."""
        if gaussians is None:
            gaussians = self.gaussians_at(t)
        image = self.model.render(gaussians, camera, self.sh_degree, self._background()).image
        return self.model.colour(image, camera_id).clamp(0, 1)

    @torch.no_grad()
    def render_labels(
        self, camera, labels: torch.Tensor, k: int, t: float | None = None, gaussians: dict | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(label image [H, W] int64 (0 background, 1 .. K segments), confidence [H, W] (the winning
        label's share of the pixel's rendered weight)) of the Gaussians at ``t`` (or ``gaussians``) with
        ``labels`` [N] in 0 .. K-1, seen by ``camera``."""
        if gaussians is None:
            gaussians = self.gaussians_at(t)
        dev = gaussians["means"].device
        one_hot = torch.nn.functional.one_hot(labels.to(dev).long(), max(k, 1)).float()  # [N, K]
        one_hot = torch.nn.functional.pad(one_hot, (0, (-one_hot.shape[1]) % 3))
        weights, alpha = [], None
        for c in range(0, one_hot.shape[1], 3):
            # the model's own render (its near plane, its backend), with label colours on no background
            out = self.model.render(gaussians, camera, 0, None, colors=one_hot[:, c : c + 3].contiguous())
            weights.append(out.image)
            alpha = out.alpha
        weight = torch.cat(weights, dim=-1)[..., :k].cpu().numpy()  # [H, W, K]
        alpha = alpha[..., 0].cpu().numpy()
        winner = weight.argmax(-1)
        confidence = np.take_along_axis(weight, winner[..., None], -1)[..., 0] / np.maximum(alpha, 1e-6)
        return np.where(alpha >= ALPHA_MIN, winner + 1, 0), np.clip(confidence, 0.0, 1.0)

    def _background(self) -> torch.Tensor:
        if self.background is None:
            return torch.zeros(3, device=self.device)
        return self.background


def _chosen_here(entry: dict | None, t0: float, n: int) -> bool:
    """Whether a stored choice (free bodies, joint parts) was made for this handover and these ``n``
    Gaussians (not for another handover or another set of Gaussians)."""
    return abs(entry["t0"] - t0) <= 1e-9 and entry["labels"].shape[0] == n
