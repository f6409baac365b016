"""What changes as a run trains, as one object: the step, the optimisers, the densification statistics,
the NaN guard's learning-rate scale and history, the random states and the time spent. The checkpoint
(``checkpoint.py``) saves it as a whole beside the model, and a run resumed from it goes on as the
uninterrupted run would (``TrainState.state_dict`` / ``TrainState.load_state_dict``)."""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass, field
from typing import Any

import torch

from ..config import OptimConfig
from ..utils import random_states, set_random_states
from .optim import colour_optimizer, field_optimizer, gaussian_optimizers
from .strategy import DefaultStrategy


@dataclass
class TrainState:
    """The mutable state of a training (module docstring); the trainer composes it with what stays put
    (the settings, the data, the model's structure, the densification strategy)."""

    optimizers: dict[str, torch.optim.Optimizer]
    """One Adam per Gaussian parameter (densification replaces their rows: ``strategy.py``)."""
    field_opt: torch.optim.Optimizer | None
    """The one Adam of both fields (None without field parameters)."""
    colour_opt: torch.optim.Optimizer | None
    """The Adam of the per-camera colours (None without them)."""
    strategy: dict[str, Any]
    """The densification statistics (``DefaultStrategy.initialize_state``)."""
    generator: torch.Generator
    """The run's seeded generator; its state is saved with the global random states."""
    step: int = 0
    """Steps trained so far (the next step's index)."""
    train_seconds: float = 0.0
    """Time spent in the steps, resumed runs and steps undone by the NaN guard included."""
    lr_scale: float = 1.0
    """Every learning rate's factor, lowered by the NaN guard (``optim.nan_lr_factor``)."""
    restorations: list[dict] = field(default_factory=list)
    """What the NaN guard restored: {"step", "to_step", "what"} each."""
    timings: defaultdict[str, float] = field(default_factory=lambda: defaultdict(float))
    """Seconds spent in each part of the steps (fields, raster_forward, backward, optimizer)."""
    static_fraction: float | None = None
    """The fraction of the Gaussians held static (``stage2.skip_static``), once marked."""

    @classmethod
    def start(
        cls, model, optim: OptimConfig, extent: float, strategy: DefaultStrategy, generator: torch.Generator
    ) -> TrainState:
        """The state of a training about to take its first step on ``model`` (fresh optimisers and
        statistics)."""
        return cls(
            optimizers=gaussian_optimizers(model.gaussians, optim, extent),
            field_opt=field_optimizer(model.field_parameter_groups(), optim),
            colour_opt=colour_optimizer(model.camera_colour, optim),
            strategy=strategy.initialize_state(),
            generator=generator,
        )

    def all_optimizers(self) -> list[torch.optim.Optimizer | None]:
        """The Gaussians' optimisers, then the fields' and the colours' (None where there is none)."""
        return [*self.optimizers.values(), self.field_opt, self.colour_opt]

    def state_dict(self, device: torch.device) -> dict:
        """The state as tensors and plain data, under the checkpoint's keys (read back with
        ``torch.load(weights_only=True)``); ``device``'s random state (CUDA) among the random states."""
        return {
            "step": self.step,
            "train_seconds": self.train_seconds,
            "timings": dict(self.timings),
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "field_optimizer": self.field_opt.state_dict() if self.field_opt is not None else None,
            "colour_optimizer": self.colour_opt.state_dict() if self.colour_opt is not None else None,
            "strategy": dict(self.strategy),
            "lr_scale": self.lr_scale,
            "restorations": list(self.restorations),
            "rng": random_states(device) | {"generator": self.generator.get_state()},
        }

    def load_state_dict(self, saved: dict, device: torch.device, static_mask: torch.Tensor | None) -> None:
        """Take the state ``state_dict`` saved (and set the random states); parts that checkpoints of
        earlier versions lack (densification statistics, NumPy's random state, the learning-rate
        scale, an optimiser's state saved without its parameter groups) keep their fresh values. ``static_mask``: the model's, whose mean is ``static_fraction``."""
        for k, o in self.optimizers.items():
            _load_optimizer(o, saved["optimizers"].get(k))
        _load_optimizer(self.field_opt, saved["field_optimizer"])
        _load_optimizer(self.colour_opt, saved.get("colour_optimizer"))
        self.strategy = self.strategy | saved.get("strategy", {})
        self.step, self.train_seconds = saved["step"], saved["train_seconds"]
        self.lr_scale = float(saved.get("lr_scale", 1.0))
        self.restorations = list(saved.get("restorations", []))
        self.timings = defaultdict(float, saved.get("timings", {}))
        self.static_fraction = None if static_mask is None else float(static_mask.float().mean())
        set_random_states(saved["rng"], device)
        if "generator" in saved["rng"]:
            self.generator.set_state(saved["rng"]["generator"].cpu())


def _load_optimizer(opt: torch.optim.Optimizer | None, saved: dict | None) -> None:
    """``opt.load_state_dict(saved)`` where both are there; an optimiser saved without its parameter
    groups (its state dropped from the checkpoint) starts afresh."""
    if opt is not None and saved is not None and saved["param_groups"]:
        opt.load_state_dict(saved)
