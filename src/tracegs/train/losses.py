"""The loss of a training step: the photometric loss of 3DGS and TRACE, (1 - w) * L1 + w * (1 - SSIM),
w = 0.2, over the step's views, and with ``optim.mask_weight`` a foreground-mask term."""

from __future__ import annotations

import torch

from ..render.ssim import training_ssim


def photometric_loss(
    image: torch.Tensor, target: torch.Tensor, ssim_weight: float = 0.2
) -> dict[str, torch.Tensor]:
    """Named loss terms for a rendered ``image`` [H, W, 3] against ``target`` [H, W, 3]; "loss" is the sum.
    SSIM is ``image_metrics.ssim``'s, by the native kernel on the CPU (``render/ssim.py``)."""
    l1 = (image - target).abs().mean()
    s = training_ssim(image, target)
    return {"l1": l1, "ssim": s.detach(), "loss": (1 - ssim_weight) * l1 + ssim_weight * (1 - s)}


def views_loss(trainer, state: dict, views: list, background: torch.Tensor) -> tuple[dict, list[dict]]:
    """The loss terms of Gaussians ``state`` rendered from ``views`` (the mean over them; the fields'
    state is shared) by ``trainer``'s model, and each view's render info for the densification. With
    ``optim.mask_weight`` and Gaussians held static (the subject is the rest), the L1 between the
    subject's own coverage and each view's foreground mask, where the view has one."""
    cfg, model = trainer.cfg, trainer.model
    infos, losses = [], {}
    for view in views:
        target = trainer.data.target(view, background) if cfg.random_background else view.image
        out = model.render(state, view.camera, trainer.sh_degree(), background)
        image = model.colour(out.image, view.camera_id)
        size = {"width": view.camera.width, "height": view.camera.height}
        infos.append({"means2d": out.means2d, "radii": out.radii, **size})
        trainer.strategy.step_pre_backward(infos[-1])
        terms = photometric_loss(image, target, cfg.optim.ssim_weight)
        if cfg.optim.mask_weight > 0 and model.static_mask is not None:
            mask = foreground_of(trainer, view)
            if mask is not None:
                coverage = model.render(state, view.camera, 0, background, rows=model.moving_rows).alpha
                terms["mask"] = (coverage[..., 0] - mask).abs().mean()
                terms["loss"] = terms["loss"] + cfg.optim.mask_weight * terms["mask"]
        for name, value in terms.items():
            value = value / len(views) if len(views) > 1 else value
            losses[name] = losses[name] + value if name in losses else value
    return losses, infos


def foreground_of(trainer, view) -> torch.Tensor | None:
    """[H, W] float foreground mask of ``view`` (read once, ``data.masks``), or None without one."""
    cache = trainer.__dict__.setdefault("_masks", {})
    if view.name not in cache:
        from ..data.masks import read_foreground

        mask = None if view.frame is None else read_foreground(trainer.cfg.data, view.frame)
        cache[view.name] = (
            None if mask is None else torch.as_tensor(mask, dtype=torch.float32).to(view.image.device)
        )
    return cache[view.name]
