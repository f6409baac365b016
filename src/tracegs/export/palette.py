"""The colour of each segment, shared by the segmentation's masks and the labelled export.

K: segments.
"""

from __future__ import annotations

import numpy as np

PALETTE = np.array(
    [
        [0.62, 0.62, 0.62],  # the static group (label 0) is grey when there is one
        [0.89, 0.10, 0.11],
        [0.22, 0.49, 0.72],
        [0.30, 0.69, 0.29],
        [1.00, 0.50, 0.00],
        [0.60, 0.31, 0.64],
        [1.00, 0.85, 0.10],
        [0.65, 0.34, 0.16],
        [0.97, 0.51, 0.75],
        [0.10, 0.75, 0.80],
    ]
)
"""Distinct RGB colours in [0, 1]: grey for a static group, then one per moving segment."""


def colours(k: int, has_static: bool) -> np.ndarray:
    """[K, 3] a distinct colour per segment (the static group grey); past the palette, a fixed random
    colour per segment."""
    start = 0 if has_static else 1
    rows = [
        PALETTE[start + i] if start + i < len(PALETTE) else np.random.default_rng(i).random(3)
        for i in range(k)
    ]
    return np.stack(rows)
