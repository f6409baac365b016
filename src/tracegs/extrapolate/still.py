"""Which Gaussians hold still after the handover, and why: one place for the rule.

A Gaussian that the learned physics would move holds still at its handover state when

* ``STATIC``: it was marked static in training (``stage2.skip_static``: f_defo never moved it);
* ``FROZEN``: f_defo's displacement up to the handover stays below the freeze threshold chosen after
  training on the training images (``extrapolation.freeze_static``);
* ``UNSEEN``: no training image showed it before the handover and f_trd, never shown it, would move it
  far faster than f_defo did (``extrapolation.hold_unseen``).

(A Gaussian that paints a still surface is stopped later, at the step that would take it off the
surface: ``surface.py``. The parts that move as free bodies are moved by ``free_bodies.py``.)
N: Gaussians.
"""

from __future__ import annotations

import torch

from ..physics.integrate import DynamicsParams, particle_velocity

MOVES, STATIC, FROZEN, UNSEEN = 0, 1, 2, 3
REASONS = {
    MOVES: "moves",
    STATIC: "static in training",
    FROZEN: "below the freeze threshold",
    UNSEEN: "unseen",
}


@torch.no_grad()
def still_codes(
    predictor, t0: float, means: torch.Tensor, params: DynamicsParams, moving: torch.Tensor | None = None
) -> torch.Tensor:
    """[N] uint8: why each Gaussian holds still after the handover ``t0`` (``MOVES`` where it moves),
    the first reason that applies in the order of the module's list. ``means`` [N, 3] and ``params``:
    f_defo's state at ``t0`` and f_trd's parameters there; ``moving`` [N] bool replaces the freeze
    threshold's choice (``FROZEN`` where false)."""
    codes = _codes(*_rules(predictor, t0, means, params, moving), means)
    return torch.zeros(means.shape[0], dtype=torch.uint8, device=means.device) if codes is None else codes


def moving_after_handover(
    predictor, t0: float, means: torch.Tensor, params: DynamicsParams, moving: torch.Tensor | None = None
) -> torch.Tensor | None:
    """[N] bool: the Gaussians the physics moves after ``t0`` (``still_codes == MOVES``); None when no
    rule holds any Gaussian still (every one moves)."""
    codes = _codes(*_rules(predictor, t0, means, params, moving), means)
    return None if codes is None else codes == MOVES


def _rules(predictor, t0, means, params, moving) -> tuple:
    """The [N] bool masks (or None where a rule does not apply) of ``STATIC``, ``FROZEN``, ``UNSEEN``
    for a ``Predictor`` (its model, post-training state and settings)."""
    model, state = predictor.model, predictor.state
    frozen = ~moving if moving is not None else _frozen(model, state, t0)
    held = _unseen_held(model, state, predictor.settings, t0, means, params)
    return model.static_mask, frozen, held


def _codes(static, frozen, unseen, means: torch.Tensor) -> torch.Tensor | None:
    """The codes of the masks, the earlier reason winning; None when no rule applies."""
    if static is None and frozen is None and unseen is None:
        return None
    codes = torch.zeros(means.shape[0], dtype=torch.uint8, device=means.device)
    for code, mask in ((UNSEEN, unseen), (FROZEN, frozen), (STATIC, static)):
        if mask is not None:
            codes[mask] = code
    return codes


def _frozen(model, state, t0: float) -> torch.Tensor | None:
    """[N] bool: below the freeze threshold at ``t0``; None when there is no threshold (or no f_defo)."""
    threshold = state.freeze_threshold or 0.0
    if threshold <= 0 or model.deformation is None:
        return None
    cache = state.cache.get("frozen")
    if (
        cache is not None
        and cache[0] == (t0, threshold)
        and cache[1].shape[0] == model.gaussians["means"].shape[0]
    ):
        return cache[1]
    frozen = ~(model.max_displacement(t0) > threshold)
    state.cache["frozen"] = ((t0, threshold), frozen)
    return frozen


def _unseen_held(
    model, state, settings, t0: float, means: torch.Tensor, params: DynamicsParams
) -> torch.Tensor | None:
    """[N] bool: unseen before the handover and moved by f_trd far faster than by f_defo; None when the
    rule is off or no Gaussian is unseen."""
    unseen = state.unseen
    if not settings.hold_unseen or unseen is None:
        return None
    if unseen.shape[0] != means.shape[0] or not bool(unseen.any()):
        return None
    return unseen & ~fields_agree(model, t0, means, params, settings.unseen_speed_ratio)


def fields_agree(model, t0: float, means: torch.Tensor, params: DynamicsParams, ratio: float) -> torch.Tensor:
    """[N] bool: f_trd's particle speed at ``t0`` is at most ``ratio`` times f_defo's mean speed over
    the 4 frames before ``t0``, plus a floor of 0.05 scene units per unit of time in the fields' frame."""
    frames = min(4.0, t0 / model.dt_max)
    if model.deformation is None or frames <= 0:
        return torch.ones(means.shape[0], dtype=torch.bool, device=means.device)
    speed_defo = (means - model.deform(t0 - frames * model.dt_max)["means"]).norm(dim=-1) / (
        frames * model.dt_max
    )
    speed_phys = particle_velocity(means, params.velocity, params.angular_velocity).norm(dim=-1)
    return speed_phys <= ratio * (speed_defo + 0.05 * float(model.field_scale))
