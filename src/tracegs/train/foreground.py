"""The split of a capture with foreground masks into what moves and what stands still, made once when
stage 2 starts (``stage2.static_outside_masks``).

The subject of a capture sweeps a region over the training span: the union of the visual hulls of its
masks at the training times (``data.hull.in_any_hull``). A Gaussian outside that region, and not
within ``stage2.static_margin`` spacings of one inside it, belongs to the surroundings: stage 1 has
fitted it to the first time's views, and from stage 2 on it keeps its canonical geometry (the static
mask of ``stage2.skip_static``), so the fields spend their capacity, and their time, on the subject.
With ``stage2.freeze_surroundings`` the surroundings are fitted once, in stage 1: from stage 2 on
their parameters take no step (``hold_surroundings``), so the dome the many first-frame views fitted
is not bent by single views of later times. Only the frames of the training window are read (a
continual round sees no later mask)."""

from __future__ import annotations

from pathlib import Path

import torch

from ..data.hull import in_any_hull
from ..models.trace import near_points


def mark_outside_masks(model, data: Path, frames: list, margin: float, log=print) -> float | None:
    """Mark static the Gaussians of ``model`` outside the region the masks of the scene ``data`` at
    ``frames`` (those of the training window) sweep, and not within ``margin`` spacings of one inside
    (module docstring); the fraction marked, or None (nothing marked) when the scene has no masks."""
    means = model.gaussians["means"].detach()
    inside = in_any_hull(data, frames, means)
    if inside is None:
        log(f"{data}: no foreground masks: stage2.static_outside_masks marks nothing")
        return None
    still = ~inside
    if margin > 0 and bool(inside.any()):
        still &= ~near_points(means, inside, margin)
    model.set_static_mask(still)
    fraction = float(still.float().mean())
    log(f"outside the region the foreground masks sweep: {fraction:.0%} of the Gaussians stand still")
    return fraction


def hold_surroundings(model, optimizers: dict[str, torch.optim.Optimizer]) -> None:
    """Zero the gradients of every parameter of ``model``'s Gaussians held static, and the first
    moments their ``optimizers`` keep (once, when the mask is new): Adam then moves them no further."""
    mask = model.static_mask
    if mask is None:
        return
    for name, param in model.gaussians.items():
        if param.grad is not None:
            param.grad[mask] = 0
        state = optimizers[name].state.get(param, {})
        if "exp_avg" in state and not state.get("held"):
            state["exp_avg"][mask] = 0
            state["held"] = True
