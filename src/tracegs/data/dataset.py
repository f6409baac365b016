"""Training views in memory: images, cameras and times of one split, ready for sampling.

V: views (images), H, W: image size.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch

from .cameras import Camera
from .frames import Frame, SceneSplit, camera_key, load_rgba
from .scene import available_splits, load_scene


@dataclass
class View:
    image: torch.Tensor  # [H, W, 3] float in [0, 1], composited on the scene background
    alpha: torch.Tensor  # [H, W, 1] coverage (1 for images without alpha)
    camera: Camera
    time: float
    camera_id: int | None
    name: str
    frame: Frame | None = None  # where it was read from (its mask, ``data/masks.py``)


class ViewDataset:
    """All images of a split (optionally only times <= ``t_max``), loaded once onto ``device``."""

    def __init__(
        self,
        root: str | Path,
        split: str = "train",
        downscale: int = 1,
        t_max: float | None = None,
        t_min: float | None = None,
        device: torch.device | str = "cpu",
        arriving: bool = False,
    ):
        """``arriving``: also the frames that the split's cameras took in the scene's other splits
        (a continual round: the same cameras keep filming past the training split's end)."""
        self.scene: SceneSplit = load_scene(root, split, downscale)
        frames = list(self.scene.frames)
        if arriving:
            cameras, paths = {camera_key(f) for f in frames}, {f.image_path for f in frames}
            for other in (s for s in available_splits(root) if s != split):
                more = load_scene(root, other, downscale).frames
                frames += [f for f in more if camera_key(f) in cameras and f.image_path not in paths]
        frames = [
            f
            for f in frames
            if (t_max is None or f.time <= t_max + 1e-9) and (t_min is None or f.time > t_min + 1e-9)
        ]
        self.background = torch.tensor(self.scene.background, dtype=torch.float32, device=device)
        self.views = []
        for f in frames:
            rgba = load_rgba(f).to(device)
            alpha = rgba[..., 3:]
            self.views.append(
                View(
                    image=rgba[..., :3] * alpha + self.background * (1 - alpha),
                    alpha=alpha,
                    camera=f.camera.to(device),
                    time=f.time,
                    camera_id=f.camera_id,
                    name=f.name,
                    frame=f,
                )
            )

    def __len__(self) -> int:
        return len(self.views)

    def __getitem__(self, i: int) -> View:
        return self.views[i]

    def target(self, view: View, background: torch.Tensor) -> torch.Tensor:
        """The view's image composited on another ``background`` [3] (random-background training)."""
        return view.image + (background - self.background) * (1 - view.alpha)

    @property
    def times(self) -> torch.Tensor:
        return torch.tensor([v.time for v in self.views])

    def by_time(self) -> dict[float, list[int]]:
        """The indices of the views at each time (the cameras of each frame)."""
        if not hasattr(self, "_by_time"):
            self._by_time: dict[float, list[int]] = {}
            for k, v in enumerate(self.views):
                self._by_time.setdefault(v.time, []).append(k)
        return self._by_time

    def same_time(self, i: int) -> list[int]:
        """The indices of the other views at view ``i``'s time (the other cameras of its frame)."""
        return [k for k in self.by_time()[self.views[i].time] if k != i]

    def camera_centers(self) -> torch.Tensor:
        return torch.stack([v.camera.center.cpu() for v in self.views])


def frame_interval(times: list[float] | torch.Tensor, fps: float | None = None) -> float:
    """Time between consecutive frames: 1 / fps if known, else the median gap of the distinct times."""
    if fps:
        return 1.0 / fps
    t = torch.unique(torch.as_tensor(times, dtype=torch.float64))
    if len(t) < 2:
        return 1.0
    return float(torch.median(t[1:] - t[:-1]))
