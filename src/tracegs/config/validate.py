"""Validation of a training config: every setting in its range before anything is read or trained.

A step count of 0 where a period is meant, a time outside (0, 1], NaN anywhere: each would otherwise
end in a ZeroDivisionError or an empty tensor deep in training. Errors name the flag as the command
line spells it (``--downscale must be a positive integer, got 0``).
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from . import TrainConfig


def _positive_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 1


def _non_negative_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and v >= 0


def _positive(v) -> bool:
    return math.isfinite(v) and v > 0


def _non_negative(v) -> bool:
    return math.isfinite(v) and v >= 0


def _unit(v) -> bool:
    return math.isfinite(v) and 0 <= v <= 1


def _train_end(v) -> bool:
    return v is None or (math.isfinite(v) and 0 < v <= 1)


RULES: dict[str, tuple] = {
    "downscale": (_positive_int, "a positive integer"),
    "static_iterations": (_non_negative_int, "a non-negative integer"),
    "dynamic_iterations": (_non_negative_int, "a non-negative integer"),
    "init_points": (_positive_int, "a positive integer"),
    "hull_resolution": (_positive_int, "a positive integer"),
    "init_surroundings": (_non_negative_int, "a non-negative integer (0 = none)"),
    "init_extent": (_positive, "a positive number"),
    "near_plane": (_positive, "a positive number"),
    "t_train_end": (_train_end, "a time in (0, 1] (the Blender / D-NeRF times)"),
    "sh_degree": (_non_negative_int, "a non-negative integer"),
    "sh_degree_interval": (_positive_int, "a positive integer"),
    "checkpoint_every": (_positive_int, "a positive integer"),
    "threads": (_non_negative_int, "a whole number >= 0 (0: chosen from the free cores)"),
    "log_every": (_positive_int, "a positive integer"),
    "optim.ssim_weight": (_unit, "in [0, 1]"),
    "optim.nan_lr_factor": (lambda v: 0 < v < 1, "in (0, 1)"),
    "densify.refine_every": (_positive_int, "a positive integer"),
    "densify.reset_every": (_non_negative_int, "a non-negative integer (0 = never)"),
    "densify.reset_opacity": (lambda v: 0 < v < 1, "in (0, 1)"),
    "densify.prune_opacity": (lambda v: 0 <= v < 1, "in [0, 1)"),
    "densify.max_gaussians": (_positive_int, "a positive integer"),
    "densify.moving_refine_stop": (_non_negative_int, "a non-negative integer (0 = off)"),
    "densify.moving_max_gaussians": (_positive_int, "a positive integer"),
    "densify.refine_stop_fraction": (_unit, "in [0, 1]"),
    "stage2.dt_frames": (_positive, "a positive number"),
    "stage2.time_growth_fraction": (_unit, "in [0, 1]"),
    "stage2.time_growth_stages": (_positive_int, "a positive integer"),
    "stage2.views_per_step": (_positive_int, "a positive integer"),
    "extrapolation.handover_frames": (_non_negative, "a non-negative number"),
    "extrapolation.surface_still_fraction": (_unit, "in [0, 1]"),
    "extrapolation.surface_neighbours": (_positive_int, "a positive integer"),
    "extrapolation.free_body_refine_views": (_positive_int, "a positive integer"),
    "extrapolation.joint_law_holdout": (lambda v: 0 < v < 1, "in (0, 1)"),
    "extrapolation.joint_law_tolerance": (_positive, "a positive number"),
    "extrapolation.joint_fit_tolerance": (_positive, "a positive number"),
}
"""The settings with a range, by dotted name, with a predicate and the range in words; besides these,
every number must be finite, and every count and learning rate non-negative (``validate``)."""


def flag_name(name: str) -> str:
    """A dotted setting as the command line spells it: ``stage2.dt_frames`` -> ``--stage2.dt-frames``."""
    return "--" + name.replace("_", "-")


def _settings(cfg, prefix: str = ""):
    """``(dotted name, value, type)`` of every leaf setting of a (nested) config dataclass (a config.json
    is read without its types: ``"method": "tarce"`` loads, so the type is checked here)."""
    hints = typing.get_type_hints(type(cfg))
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if dataclasses.is_dataclass(value):
            yield from _settings(value, f"{prefix}{f.name}.")
        else:
            yield prefix + f.name, value, hints[f.name]


def _problem(name: str, value) -> str | None:
    """What is wrong with one setting's ``value``, in words (``must be ...``), or None."""
    if name in RULES:
        ok, requirement = RULES[name]
        try:
            good = ok(value)
        except TypeError:
            good = False
        return None if good else f"must be {requirement}"
    if isinstance(value, bool) or not isinstance(value, (int, float)) or name == "seed":
        return None
    if isinstance(value, float) and not math.isfinite(value):
        return "must be a finite number"
    if value < 0 and (isinstance(value, int) or name.endswith("_lr") or "_lr_" in name):
        return "must not be negative"
    return None


def check_setting(name: str, value, flag: str | None = None) -> None:
    """Raise ValueError (``FLAG must be ..., got VALUE``) unless ``value`` is valid for the dotted
    setting ``name``; ``flag``: how the command line spells it (default: ``--`` + the dotted name)."""
    problem = _problem(name, value)
    if problem:
        raise ValueError(f"{flag or flag_name(name)} {problem}, got {value!r}")


def check_choices(cfg: TrainConfig) -> None:
    """Raise ValueError unless every setting with named choices (a ``Literal`` type) holds one of them."""
    for name, value, kind in _settings(cfg):
        allowed = typing.get_args(kind)
        if typing.get_origin(kind) is typing.Literal and value not in allowed:
            raise ValueError(
                f"{flag_name(name)} must be one of {', '.join(map(str, allowed))}, got {value!r}"
            )


def validate(cfg: TrainConfig) -> TrainConfig:
    """Check every setting of ``cfg`` before anything is trained; returns ``cfg``.

    Raises ValueError with one line naming the flag as the command line spells it and the value, e.g.
    ``--downscale must be a positive integer, got 0``. A step count of 0 where a period is meant, a time
    outside (0, 1], NaN anywhere: each would otherwise end in a ZeroDivisionError or an empty tensor deep
    in training."""
    for name, value, _ in _settings(cfg):
        check_setting(name, value)
    check_choices(cfg)
    if cfg.total_iterations < 1:
        raise ValueError(
            f"--static-iterations + --dynamic-iterations must be at least 1, got {cfg.total_iterations}"
        )
    if cfg.method == "static" and cfg.static_iterations < 1:
        raise ValueError(
            f"--static-iterations must be at least 1 with --method static, got {cfg.static_iterations}"
        )
    stop = min(cfg.densify.refine_stop, int(cfg.densify.refine_stop_fraction * cfg.total_iterations))
    if cfg.stage2.static_outside_masks and stop > cfg.static_iterations and cfg.method != "static":
        raise ValueError(
            "--stage2.static-outside-masks needs densification to stop by stage 2: --densify.refine-stop "
            f"{cfg.densify.refine_stop} is past --static-iterations {cfg.static_iterations}"
        )
    return cfg
