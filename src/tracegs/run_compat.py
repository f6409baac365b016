"""Run folders written by earlier versions of tracegs: their config's names, and the post-training
state their checkpoints held, translated to the current layout. Kept apart from ``run.py`` so that the
current layout reads on its own; a setting this version no longer has is accepted at the value that
made it a no-op, and otherwise refused by name.
"""

from __future__ import annotations

import copy

import torch

from .extrapolate import ExtrapolationState
from .physics.free_body import FREE_BODY_NUMBERS

STAGE2 = (
    "dt_frames",
    "integrator",
    "use_deformation",
    "physics_derivation",
    "time_growth_fraction",
    "time_growth_stages",
    "acceleration_consistency",
    "consistency_frames",
)
EXTRAPOLATION = (
    "handover_frames",
    "surface_neighbours",
    "free_bodies",
    "free_body_window",
    "free_body_backtest",
    "free_body_refine_steps",
    "free_body_refine_views",
    "free_body_isolation",
    "free_body_tolerance",
)
REMOVED = {
    # name: the value at which the removed setting changed nothing
    "straight_through": True,
    "straight_through_time": "t_prime",
    "consistency_transport": "dynamics",
    "angular_acceleration_penalty": 0.0,
    "rotation_consistency": 0.0,
    "rotation_neighbours": None,
    "hold_gaussians_steps": 0,
    "warmup_deformation_steps": 0,
    "extrapolation_requery": False,
    "freeze_static_threshold": 0.0,
}


def migrate_config(data: dict) -> dict:
    """Saved config data with the ``dynamic`` section of versions before the ``stage2`` /
    ``extrapolation`` split translated; data of the current layout is returned as it is. ValueError
    names a removed setting that the run used."""
    if "dynamic" not in data:
        return data
    data = copy.deepcopy(data)
    old = data.pop("dynamic")
    stage2, extrapolation = data.setdefault("stage2", {}), data.setdefault("extrapolation", {})
    for key, value in old.items():
        if key in STAGE2:
            stage2[key] = value
        elif key in EXTRAPOLATION:
            extrapolation[key] = value
        elif key == "skip_static":
            stage2["skip_static"] = value > 0
            if value > 0:
                stage2["static_displacement"] = value
        elif key == "hold_unseen":
            extrapolation["hold_unseen"] = value > 0
            if value > 0:
                extrapolation["unseen_speed_ratio"] = value
        elif key == "stay_on_surface":
            extrapolation["hold_surface"] = value > 0
            if value > 0:
                extrapolation["surface_still_fraction"] = value
        elif key == "freeze_static_auto":
            extrapolation["freeze_static"] = bool(value)
        elif key in REMOVED:
            if REMOVED[key] is not None and value != REMOVED[key]:
                raise ValueError(
                    f"the run was trained with dynamic.{key} = {value!r}, a setting this version of "
                    "tracegs no longer has; train it again"
                )
        else:
            raise ValueError(f"unknown config field DynamicStageConfig.{key}")
    return data


def state_from_old_checkpoint(ckpt: dict, device) -> ExtrapolationState | None:
    """The post-training state that checkpoints of earlier versions held among their keys, or None
    where it was incomplete (or its free bodies of an older layout): then ``tracegs calibrate``."""
    if "freeze_threshold" not in ckpt or "unseen_mask" not in ckpt or "free_bodies" not in ckpt:
        return None
    cfg = ckpt.get("config") or {}
    old = cfg.get("dynamic", {})
    if old.get("freeze_static_auto", True) and ckpt["freeze_threshold"] is None:
        return None
    if old.get("hold_unseen", 10.0) > 0 and ckpt["unseen_mask"] is None:
        return None
    bodies = ckpt["free_bodies"]
    if old.get("free_bodies", False) and (bodies is None or bodies["bodies"].shape[-1] != FREE_BODY_NUMBERS):
        return None
    if bodies is not None:
        bodies = {**bodies, "labels": bodies["labels"].to(device)}
    unseen = ckpt["unseen_mask"]
    return ExtrapolationState(
        t_max=float(ckpt["t_max"]),
        freeze_threshold=ckpt["freeze_threshold"],
        unseen=None if unseen is None else torch.as_tensor(unseen).to(device),
        free_bodies=bodies,
    )
