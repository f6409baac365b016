"""Foreground masks are found beside the images in both layouts, reduced with the images, and a bad
one is named."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from tracegs.data.cameras import Camera
from tracegs.data.frames import DatasetError, Frame
from tracegs.data.masks import foreground_path, read_foreground


def _frame(path, size=4, downscale=1):
    camera = Camera(torch.eye(4), torch.eye(3), size, size)
    return Frame(path, 0.0, camera, 0, None, downscale)


def test_masks_beside_the_images_in_both_layouts(tmp_path):
    mask = np.zeros((8, 8), np.uint8)
    mask[:4] = 255
    (tmp_path / "pan" / "seg" / "0").mkdir(parents=True)
    imageio.imwrite(tmp_path / "pan" / "seg" / "0" / "000.png", mask)
    frame = _frame(tmp_path / "pan" / "ims" / "0" / "000.jpg", size=4, downscale=2)
    assert foreground_path(tmp_path / "pan", frame) == (tmp_path / "pan" / "seg" / "0" / "000.png").resolve()
    fg = read_foreground(tmp_path / "pan", frame)
    assert fg.shape == (4, 4) and fg[:2].all() and not fg[2:].any()
    (tmp_path / "bl" / "masks" / "train").mkdir(parents=True)
    imageio.imwrite(tmp_path / "bl" / "masks" / "train" / "r_0.png", mask[:4, :4])
    frame = _frame(tmp_path / "bl" / "train" / "r_0.png")
    assert read_foreground(tmp_path / "bl", frame).all()
    assert read_foreground(tmp_path / "bl", _frame(tmp_path / "bl" / "train" / "r_1.png")) is None
    imageio.imwrite(tmp_path / "bl" / "masks" / "train" / "r_2.png", np.zeros((5, 3), np.uint8))
    with pytest.raises(DatasetError, match="r_2.png: mask of 3x5"):
        read_foreground(tmp_path / "bl", _frame(tmp_path / "bl" / "train" / "r_2.png"))
