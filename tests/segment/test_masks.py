"""Masks rendered through the rasteriser at a future time cover the parts' ground-truth positions
there; the ground-truth layout (gt/masks, gt/motion.json, Panoptic seg/) is read and merged as
documented."""

from __future__ import annotations

import json
from types import MethodType, SimpleNamespace

import numpy as np
import pytest
import torch

from tracegs.data.frames import DatasetError
from tracegs.data.scene import load_scene
from tracegs.data.synth import part_transforms, synthesize
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.models.trace import TraceModel
from tracegs.segment.masks import colour_image, colours, overlay
from tracegs.segment.truth import find_ground_truth, merged_parts


@pytest.fixture(scope="module")
def slider(tmp_path_factory):
    root = tmp_path_factory.mktemp("slider") / "scene"
    return synthesize("slider", root, resolution=64, views=4, frames=8, progress=False, spp=1)


def gaussians_of_the_parts(root, t: float):
    """Gaussians on the ground-truth surface points, carried to time ``t`` by each part's exact motion,
    and the part of each (0-based), with a stand-in for a model's opacities and backend."""
    data = np.load(root / "gt" / "points.npz")
    points, parts = data["points"], data["part_ids"]
    transforms = part_transforms(root, t)  # [P, 4, 4]
    T = transforms[parts - 1]
    moved = np.einsum("nij,nj->ni", T[:, :3, :3], points) + T[:, :3, 3]
    n = len(points)
    gaussians = {
        "means": torch.tensor(moved, dtype=torch.float32),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        "scales": torch.full((n, 3), float(np.log(0.01))),
    }
    return stand_in_model(n), gaussians, torch.tensor(parts - 1)


def stand_in_model(n: int, near: float = 0.01) -> SimpleNamespace:
    """A stand-in for a trained model of ``n`` Gaussians (opacity 0.5) with ``TraceModel.render``, the
    near plane ``near`` and the default backend."""
    gaussians = {"opacities": torch.zeros(n), "sh0": torch.zeros(n, 1, 3), "shN": torch.zeros(n, 0, 3)}
    model = SimpleNamespace(
        gaussians=gaussians, cfg=SimpleNamespace(backend="auto"), backend="auto", _near=near
    )
    model.render = MethodType(TraceModel.render, model)
    return model


def test_future_masks_cover_the_parts_ground_truth_positions(slider):
    truth = find_ground_truth(slider)
    assert truth.layout == "parts" and truth.merged == []
    test = load_scene(slider, "test")
    t = max(f.time for f in test.frames)
    assert t > test.frames[0].time - 1e-9 and t == pytest.approx(1.0)
    model, gaussians, labels = gaussians_of_the_parts(slider, t)
    shown, found = np.zeros(4), np.zeros(4)
    for frame in [f for f in test.frames if f.time == t]:
        pred, confidence = render_labels(model, gaussians, labels, 3, frame.camera)
        gt = truth.read(frame)
        assert gt.shape == pred.shape == confidence.shape
        for part in (1, 2, 3):
            shown[part] += (gt == part).sum()
            found[part] += (pred[gt == part] == part).sum()
        assert ((pred > 0) == (gt > 0)).mean() > 0.93  # the background where nothing is
    # each part's ground-truth pixels are rendered as that part (the rest: the rasteriser's 0.3 px
    # blur at the parts' edges, and surface points seen through the sparse cloud)
    assert (found[1:] / shown[1:] > 0.85).all(), found / np.maximum(shown, 1)


def test_masks_follow_the_motion(slider):
    """The same Gaussians left at t = 0 miss where the carriage is at t = 1: the test is not blind."""
    truth = find_ground_truth(slider)
    frame = [f for f in load_scene(slider, "test").frames if f.time == 1.0][0]
    model, g_end, labels = gaussians_of_the_parts(slider, 1.0)
    _, g_start, _ = gaussians_of_the_parts(slider, 0.0)
    gt = truth.read(frame)
    at_end = render_labels(model, g_end, labels, 3, frame.camera)[0]
    at_start = render_labels(model, g_start, labels, 3, frame.camera)[0]
    carriage = gt == 2
    assert (at_end[carriage] == 2).mean() > (at_start[carriage] == 2).mean() + 0.2


def test_masks_are_drawn_with_the_runs_near_plane(slider):
    """A capture's run draws nothing nearer its cameras than its near plane (``capture``: 0.6, for
    cameras among the walls); its masks neither. A still Gaussian 0.3 in front of the camera covers
    the view under the rasteriser's default 0.01, and is culled under the run's plane."""
    frame = [f for f in load_scene(slider, "test").frames if f.time == 1.0][0]
    _, g, labels = gaussians_of_the_parts(slider, 1.0)
    camera = frame.camera
    ahead = camera.center + 0.3 * torch.linalg.inv(camera.viewmat[:3, :3])[:, 2]  # 0.3 along the view
    g = {"means": torch.cat([g["means"], ahead[None].float()]), "quats": torch.cat([g["quats"], g["quats"][:1]]),
         "scales": torch.cat([g["scales"], torch.full((1, 3), float(np.log(0.5)))])}  # fmt: skip
    labels = torch.cat([labels, torch.tensor([0])])
    truth = find_ground_truth(slider).read(frame)
    for near, covered in ((0.01, True), (0.6, False)):
        model = stand_in_model(len(labels), near)
        model.gaussians["opacities"][-1] = 10.0  # opaque
        pred = render_labels(model, g, labels, 3, camera)[0]
        carriage = truth == 2
        assert ((pred[carriage] == 2).mean() < 0.1) == covered, near


def test_static_and_alike_parts_merge(tmp_path):
    parts = [
        {"id": 1, "name": "floor", "type": "static"},
        {"id": 2, "name": "door", "type": "hinge", "w": 1.0},
        {"id": 3, "name": "table", "type": "static"},
        {"id": 4, "name": "handle", "type": "hinge", "w": 1.0},
        {"id": 5, "name": "wheel", "type": "hinge", "w": 2.0},
    ]
    (tmp_path / "motion.json").write_text(json.dumps({"parts": parts}))
    segment_of, merged = merged_parts(tmp_path / "motion.json")
    assert segment_of == {1: 1, 3: 1, 2: 2, 4: 2, 5: 5}
    assert merged == [["floor", "table"], ["door", "handle"]]
    assert merged_parts(tmp_path / "absent.json") == ({}, [])
    (tmp_path / "bad.json").write_text(json.dumps({"parts": [{"name": "x"}]}))
    with pytest.raises(DatasetError, match="bad.json"):
        merged_parts(tmp_path / "bad.json")


def test_a_mask_of_the_wrong_size_names_the_file(slider, tmp_path):
    import shutil

    import imageio.v3 as iio

    copy = shutil.copytree(slider, tmp_path / "copy")
    frame = load_scene(copy, "train").frames[0]
    truth = find_ground_truth(copy)
    iio.imwrite(truth.mask_path(frame), np.zeros((7, 5), np.uint8))
    with pytest.raises(DatasetError, match=truth.mask_path(frame).name):
        truth.read(frame)
    assert find_ground_truth(tmp_path / "nothing") is None


def test_foreground_layout(tmp_path):
    """A Panoptic capture's seg/ masks are foreground / background, read beside ims/."""
    import imageio.v3 as iio

    from tests.conftest import write_tiny_scene
    from tests.data.test_panoptic import write_panoptic

    root = write_panoptic(tmp_path / "cap", write_tiny_scene(tmp_path / "blender"))
    assert find_ground_truth(root) is None  # no seg/ yet
    (root / "seg").mkdir()
    frame = load_scene(root, "train").frames[0]
    truth = find_ground_truth(root)
    assert truth.layout == "foreground"
    mask = np.zeros((frame.height, frame.width), bool)
    mask[: frame.height // 2] = True
    path = truth.mask_path(frame)
    path.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(path, mask)
    assert set(np.unique(truth.read(frame))) == {0, 1}


def test_overlay_and_colours():
    palette = colours(3, has_static=True)
    assert palette.shape == (3, 3) and np.allclose(palette[0], palette[0].mean())  # static grey
    labels = np.array([[0, 1], [2, 3]])
    image = np.zeros((2, 2, 3))
    out = overlay(image, labels, palette)
    assert (out[0, 0] == 0).all() and (out[1, 1] > 0).any()  # background untouched
    assert np.allclose(colour_image(labels, palette)[0, 0], 1.0)


def test_masks_of_a_downscaled_run_are_sampled_down(slider):
    """A run trained with --downscale 2 reads the full-size masks by nearest sampling."""
    truth = find_ground_truth(slider)
    full = load_scene(slider, "train").frames[0]
    half = load_scene(slider, "train", downscale=2).frames[0]
    big, small = truth.read(full), truth.read(half)
    assert small.shape == (full.height // 2, full.width // 2)
    assert (small == big[1::2, 1::2]).all()


def render_labels(model, gaussians: dict, labels: torch.Tensor, k: int, camera):
    """The label image and confidence of ``gaussians`` with ``labels``, as the trained run of ``model``
    renders them (``Predictor.render_labels``)."""
    return Predictor(model, ExtrapolationState(t_max=1.0)).render_labels(
        camera, labels, k, gaussians=gaussians
    )
