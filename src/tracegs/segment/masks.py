"""2D segmentation masks drawn over images. The masks themselves are rendered by the trained run
(``extrapolate.Predictor.render_labels``) through the same rasteriser as the images: each Gaussian
carries its label as a one-hot colour (three labels per pass), the label with the largest rendered
weight wins each pixel, and pixels whose accumulated opacity stays below ``ALPHA_MIN`` are
background (label 0; segments are 1 .. K, as the ground truth's part ids).

K: segments, H, W: image size.
"""

from __future__ import annotations

import numpy as np

from ..export.palette import colours as colours  # segment's palette is the labelled export's


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
