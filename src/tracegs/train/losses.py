"""The loss of a training step: the photometric loss of 3DGS and TRACE, (1 - w) * L1 + w * (1 - SSIM),
w = 0.2, over the step's views, and with ``optim.mask_weight`` a foreground-mask term."""

from __future__ import annotations

from pathlib import Path

import torch

from ..config import OptimConfig
from ..data.dataset import ViewDataset
from ..render.ssim import training_ssim
from .strategy import DefaultStrategy


def photometric_loss(
    image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2
) -> dict[str, torch.Tensor]:
    """Named loss terms for a rendered ``image`` [H, W, 3] against ``target`` [H, W, 3]; "loss" is the sum.
    SSIM is ``image_metrics.ssim``'s, by the native kernel on the CPU (``render/ssim.py``)."""
    l1 = (image - target).abs().mean()
    s = training_ssim(image, target)
    return {"l1": l1, "ssim": s.detach(), "loss": (1 - ssim_weight) * l1 + ssim_weight * (1 - s)}


def views_loss(
    model,
    state: dict,
    views: list,
    background: torch.Tensor,
    sh_degree: int,
    optim: OptimConfig,
    strategy: DefaultStrategy,
    targets: ViewDataset | None = None,
    masks: ForegroundMasks | None = None,
) -> tuple[dict, list[dict]]:
    """The loss terms of Gaussians ``state`` rendered from ``views`` (the mean over them; the fields'
    state is shared) by ``model`` at ``sh_degree``, and each view's render info for ``strategy``'s
    densification. ``targets``: the dataset whose images are composited on ``background`` (random-
    background training), else each view's own image is the target. With ``optim.mask_weight`` and
    Gaussians held static (the subject is the rest), the L1 between the subject's own coverage and each
    view's foreground mask (of ``masks``), where the view has one."""
    infos, losses = [], {}
    for view in views:
        target = targets.target(view, background) if targets is not None else view.image
        out = model.render(state, view.camera, sh_degree, background)
        image = model.colour(out.image, view.camera_id)
        size = {"width": view.camera.width, "height": view.camera.height}
        infos.append({"means2d": out.means2d, "radii": out.radii, **size})
        strategy.step_pre_backward(infos[-1])
        terms = photometric_loss(image, target, optim.ssim_weight)
        if optim.mask_weight > 0 and model.static_mask is not None and masks is not None:
            mask = masks(view)
            if mask is not None:
                coverage = model.render(state, view.camera, 0, background, rows=model.moving_rows).alpha
                terms["mask"] = (coverage[..., 0] - mask).abs().mean()
                terms["loss"] = terms["loss"] + optim.mask_weight * terms["mask"]
        for name, value in terms.items():
            value = value / len(views) if len(views) > 1 else value
            losses[name] = losses[name] + value if name in losses else value
    return losses, infos


class ForegroundMasks:
    """The foreground masks of a scene's views (``data.masks``), each read once."""

    def __init__(self, data: Path):
        self.data = Path(data)
        self._masks: dict[str, torch.Tensor | None] = {}

    def __call__(self, view) -> torch.Tensor | None:
        """[H, W] float foreground mask of ``view``, on its image's device, or None without one."""
        if view.name not in self._masks:
            from ..data.masks import read_foreground

            mask = None if view.frame is None else read_foreground(self.data, view.frame)
            self._masks[view.name] = (
                None if mask is None else torch.as_tensor(mask, dtype=torch.float32).to(view.image.device)
            )
        return self._masks[view.name]
