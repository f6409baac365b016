"""2D segmentation masks at any time, rendered through the same rasteriser as the images: each Gaussian
carries its label as a one-hot colour (three labels per pass), the label with the largest rendered
weight wins each pixel, and pixels whose accumulated opacity stays below ``ALPHA_MIN`` are
background (label 0; segments are 1 .. K, as the ground truth's part ids).

K: segments, H, W: image size.
"""

from __future__ import annotations

import numpy as np
import torch

from ..export.palette import colours as colours  # segment's palette is the labelled export's

ALPHA_MIN = 0.5
"""Pixels less opaque than this are background."""


@torch.no_grad()
def render_labels(
    model, gaussians: dict[str, torch.Tensor], labels: torch.Tensor, k: int, camera
) -> tuple[np.ndarray, np.ndarray]:
    """(label image [H, W] int64 (0 background, 1 .. K segments), confidence [H, W] (the winning
    label's share of the pixel's rendered weight)) of the Gaussians ``gaussians`` (geometry at some
    time, e.g. ``extrapolate.gaussians_at``) with ``labels`` [N] in 0 .. K-1, seen by ``camera``."""
    dev = gaussians["means"].device
    one_hot = torch.nn.functional.one_hot(labels.to(dev).long(), max(k, 1)).float()  # [N, K]
    pad = (-one_hot.shape[1]) % 3
    one_hot = torch.nn.functional.pad(one_hot, (0, pad))
    weights, alpha = [], None
    for c in range(0, one_hot.shape[1], 3):
        # the model's own render (its near plane, its backend), with label colours on no background
        out = model.render(gaussians, camera, 0, None, colors=one_hot[:, c : c + 3].contiguous())
        weights.append(out.image)
        alpha = out.alpha
    weight = torch.cat(weights, dim=-1)[..., :k].cpu().numpy()  # [H, W, K]
    alpha = alpha[..., 0].cpu().numpy()
    winner = weight.argmax(-1)
    confidence = np.take_along_axis(weight, winner[..., None], -1)[..., 0] / np.maximum(alpha, 1e-6)
    return np.where(alpha >= ALPHA_MIN, winner + 1, 0), np.clip(confidence, 0.0, 1.0)


def overlay(
    image: np.ndarray, label_image: np.ndarray, palette: np.ndarray, strength: float = 0.55
) -> np.ndarray:
    """The rendered ``image`` [H, W, 3] in [0, 1] tinted by each pixel's segment colour (``palette``
    [K, 3]; label 0 background untouched)."""
    tint = np.concatenate([np.zeros((1, 3)), palette])[label_image]
    mix = np.where((label_image > 0)[..., None], (1 - strength) * image + strength * tint, image)
    return np.clip(mix, 0.0, 1.0)


def colour_image(label_image: np.ndarray, palette: np.ndarray, background=(1.0, 1.0, 1.0)) -> np.ndarray:
    """[H, W, 3] each pixel in its segment's colour, the background in ``background``."""
    return np.concatenate([np.asarray(background, dtype=np.float64)[None], palette])[label_image]
