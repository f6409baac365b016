"""Images of every common layout load as RGBA in [0, 1]; bad ones are refused naming the file; the
rules of times and file paths in a split file."""

from __future__ import annotations

import json
import os

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from tests.bad_input.images import write_png16

from tracegs.data.scene import DatasetError, load_rgba, load_scene


def _frame(scene, k=0, downscale=1):
    return load_scene(scene, "train", downscale).frames[k]


def _source(scene, k=0):
    frame = _frame(scene, k)
    return frame.image_path, iio.imread(frame.image_path)  # [H, W, 4] uint8


LAYOUTS = {
    # name: (write the layout from RGBA uint8, the RGBA in [0, 1] expected from that RGBA)
    "grey": (
        lambda p, a: iio.imwrite(p, a[..., 0]),
        lambda a: np.concatenate([np.repeat(a[..., :1] / 255, 3, -1), np.ones_like(a[..., :1])], -1),
    ),
    "grey 16-bit": (
        lambda p, a: iio.imwrite(p, a[..., 0].astype(np.uint16) * 257),
        lambda a: np.concatenate([np.repeat(a[..., :1] / 255, 3, -1), np.ones_like(a[..., :1])], -1),
    ),
    "RGB": (
        lambda p, a: iio.imwrite(p, a[..., :3]),
        lambda a: np.concatenate([a[..., :3] / 255, np.ones_like(a[..., :1])], -1),
    ),
    "RGBA 16-bit": (lambda p, a: write_png16(p, a.astype(np.uint16) * 257), lambda a: a / 255),
    "grey + alpha 16-bit": (
        lambda p, a: write_png16(p, a[..., [0, 3]].astype(np.uint16) * 257),
        lambda a: np.concatenate([np.repeat(a[..., :1], 3, -1), a[..., 3:]], -1) / 255,
    ),
}


@pytest.mark.parametrize("write, expected", LAYOUTS.values(), ids=list(LAYOUTS))
def test_every_image_layout_loads_as_rgba(tiny_scene, write, expected):
    path, rgba = _source(tiny_scene)
    write(path, rgba)
    loaded = load_rgba(_frame(tiny_scene)).numpy()
    assert loaded.shape == rgba.shape and loaded.dtype == np.float32
    # 16-bit RGB(A) files are decoded at 8 bits by Pillow: within one step of 1/255
    assert np.abs(loaded - expected(rgba)).max() <= 1 / 255 + 1e-6


def test_a_downscale_that_does_not_divide_the_image_is_refused(tiny_scene):
    with pytest.raises(DatasetError, match="--downscale 5 does not divide the image size 24x24"):
        load_rgba(_frame(tiny_scene, downscale=5))
    half = load_rgba(_frame(tiny_scene, downscale=2))
    full = load_rgba(_frame(tiny_scene))
    assert half.shape == (12, 12, 4)
    assert torch.allclose(half[..., 3], full[..., 3].reshape(12, 2, 12, 2).mean((1, 3)), atol=1e-6)


def test_an_image_of_another_size_in_the_split_is_refused(tiny_scene):
    path, rgba = _source(tiny_scene, 1)
    iio.imwrite(path, np.concatenate([rgba, rgba], axis=0))  # twice as tall: no --downscale explains it
    with pytest.raises(DatasetError, match=r"c0_f1.png: image is 24x48, expected 24x24"):
        load_rgba(_frame(tiny_scene, 1))


def _edit(scene, edit):
    path = scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def test_times_are_all_given_or_none(tiny_scene):
    _edit(tiny_scene, lambda m: m["frames"][4].pop("time"))
    with pytest.raises(DatasetError, match="frame 4: no 'time'"):
        load_scene(tiny_scene, "train")
    _edit(tiny_scene, lambda m: [f.pop("time", None) for f in m["frames"]])
    assert [f.time for f in load_scene(tiny_scene, "train").frames] == [0.0] * 9


def test_a_symlinked_image_inside_the_scene_is_read_and_an_escaping_path_is_not(tiny_scene, tmp_path):
    elsewhere = tmp_path / "elsewhere.png"
    path, rgba = _source(tiny_scene)
    iio.imwrite(elsewhere, rgba)
    path.unlink()
    os.symlink(elsewhere, path)  # a scene folder may link its images from elsewhere
    assert torch.equal(load_rgba(_frame(tiny_scene)), torch.from_numpy(rgba / np.float32(255)))
    _edit(tiny_scene, lambda m: m["frames"][0].update(file_path="train/../../elsewhere.png"))
    with pytest.raises(DatasetError, match="leaves the scene folder"):
        load_scene(tiny_scene, "train")
    _edit(tiny_scene, lambda m: m["frames"][0].update(file_path="./train/../train/c0_f0.png"))
    assert load_scene(tiny_scene, "train").frames[0].image_path.name == "c0_f0.png"
