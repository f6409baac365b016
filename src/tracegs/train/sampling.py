"""What a step trains on: its views (stage 1: the first time's; stage 2: a time in the growing time range
and other cameras' views of it), the time t' the fields integrate from, and the time the acceleration
consistency reads them again. Each draws from Python's ``random`` (saved in the checkpoint)."""

from __future__ import annotations

import math
import random

from ..config import Stage2Config
from ..data.dataset import ViewDataset


def views_per_step(data: ViewDataset, stage2: Stage2Config) -> int:
    """Views a stage-2 step renders: ``stage2.views_per_step``, at most the median number of cameras
    that saw a time (a monocular video has one)."""
    counts = sorted(len(v) for v in data.by_time().values())  # cameras per time
    return max(1, min(stage2.views_per_step, counts[len(counts) // 2]))


def dynamic_steps(method: str, dynamic_iterations: int, stage2: Stage2Config, per_step: int) -> int:
    """Steps of stage 2: as many views as ``dynamic_iterations`` steps of ``stage2.views_per_step``
    views would render (more steps where fewer cameras saw a time); none for the static method."""
    views = dynamic_iterations * stage2.views_per_step
    return 0 if method == "static" else math.ceil(views / per_step)


class StepSampler:
    """The views and times of the steps of a training on ``data`` (module docstring)."""

    def __init__(
        self,
        data: ViewDataset,
        stage2: Stage2Config,
        dynamic_steps: int,
        views_per_step: int,
        t_max: float,
        dt_frame: float,
    ):
        self.data, self.stage2 = data, stage2
        self.dynamic_steps, self.views_per_step = dynamic_steps, views_per_step
        self.t_max, self.dt_frame = t_max, dt_frame
        self.static_views = static_views(data)
        self._allowed: tuple = (None, [])  # the views of the current time range (``dynamic_view``)

    def static_view(self) -> int:
        """A training image of stage 1."""
        return random.choice(self.static_views)

    def time_limit(self, dyn_step: int) -> float:
        """End of the sampled time range at a dynamic step: it grows in ``stage2.time_growth_stages``
        equal steps over the first ``stage2.time_growth_fraction`` of the stage."""
        growth = self.stage2.time_growth_fraction * self.dynamic_steps
        stages = self.stage2.time_growth_stages
        frac = 1.0 if growth <= 0 else min(1.0, (1 + (stages * dyn_step) // growth) / stages)
        return self.t_max * frac

    def growth_steps(self) -> int:
        """The dynamic steps after which the sampled time range covers the training span."""
        return math.ceil(self.stage2.time_growth_fraction * self.dynamic_steps)

    def dynamic_view(self, dyn_step: int) -> int:
        """A training image whose time lies in the current (growing) time range."""
        limit = self.time_limit(dyn_step) + 1e-9
        key = (limit, id(self.data), len(self.data.views))  # (the list changes with the time range only)
        if self._allowed[0] != key:
            self._allowed = (key, [i for i, v in enumerate(self.data.views) if v.time <= limit])
        return random.choice(self._allowed[1])

    def views_at_time(self, index: int) -> list:
        """View ``index`` and up to ``views_per_step`` - 1 other cameras' views at its time, at random."""
        extra, chosen = self.views_per_step - 1, []
        if extra > 0:  # (the one-view step looks up nothing)
            others = self.data.same_time(index)
            chosen = random.sample(others, min(extra, len(others)))
        return [self.data[i] for i in [index, *chosen]]

    def t_prime(self, t: float) -> float:
        """t' = t -/+ dt with a random sign, kept inside [0, t_max]."""
        dt = self.stage2.dt_frames * self.dt_frame
        sign = random.choice((-1.0, 1.0))
        t_prime = t - sign * dt
        if not 0.0 <= t_prime <= self.t_max:
            t_prime = t + sign * dt
        return min(max(t_prime, 0.0), self.t_max)

    def consistency_time(self, t_prime: float, t: float, limit: float) -> float:
        """Where the acceleration consistency reads f_trd again: ``stage2.consistency_frames`` frame
        intervals from t' in the direction of t (the other way where that leaves [0, ``limit``],
        clamped), or t itself when the setting is 0."""
        frames = self.stage2.consistency_frames
        if frames <= 0 or t == t_prime:
            return t
        span = math.copysign(frames * self.dt_frame, t - t_prime)
        t_check = t_prime + span
        if not 0.0 <= t_check <= limit:
            t_check = t_prime - span
        return min(max(t_check, 0.0), max(limit, t))


def static_views(data: ViewDataset) -> list[int]:
    """Stage 1 uses the images at the first time if at least 3 cameras saw it (multi-view
    capture), else all training images (a monocular video has a single view per time)."""
    t0 = min(v.time for v in data.views)
    first = [i for i, v in enumerate(data.views) if abs(v.time - t0) < 1e-9]
    return first if len(first) >= 3 else list(range(len(data)))
