"""The Dynamic 3D Gaussians layout (CMU Panoptic Sports): the same cameras, times and images as the
Blender-format scene it is written from, and clear errors for malformed files."""

import json
import shutil

import pytest
import torch
from tests.conftest import write_tiny_scene

from tracegs.data.scene import DatasetError, available_splits, load_rgba, load_scene
from tracegs.eval.protocol import split_frames


def write_panoptic(root, blender):
    """``blender`` (a tiny Blender-format scene, 4 cameras x 4 times) rewritten in the layout: cameras
    0-2 at every time in ``train_meta.json``, camera 3 in ``test_meta.json``."""
    frames = [f for split in ("train", "val", "test") for f in load_scene(blender, split).frames]
    times = sorted({f.time for f in frames})
    by_key = {(f.camera_id, f.time): f for f in frames}
    for split, cams in (("train", [0, 1, 2]), ("test", [3])):
        meta = {"w": 24, "h": 24, "k": [], "w2c": [], "fn": [], "cam_id": []}
        for i, t in enumerate(times):
            rows = [by_key[c, t] for c in cams]
            meta["k"].append([f.camera.K.tolist() for f in rows])
            meta["w2c"].append([f.camera.viewmat.tolist() for f in rows])
            meta["fn"].append([f"{c}/{i:06d}.png" for c in cams])
            meta["cam_id"].append(cams)
            for c, f in zip(cams, rows, strict=True):
                (root / "ims" / str(c)).mkdir(parents=True, exist_ok=True)
                shutil.copy(f.image_path, root / "ims" / str(c) / f"{i:06d}.png")
        (root / f"{split}_meta.json").write_text(json.dumps(meta))
    return root


@pytest.fixture
def scenes(tmp_path):
    blender = write_tiny_scene(tmp_path / "blender")
    return blender, write_panoptic(tmp_path / "panoptic", blender)


def test_reads_the_same_cameras_times_and_images(scenes):
    blender, panoptic = scenes
    assert available_splits(panoptic) == ["train", "test"]
    split = load_scene(panoptic, "train")
    assert len(split.frames) == 12 and len({f.name for f in split.frames}) == 12
    assert sorted({f.time for f in split.frames}) == pytest.approx([0, 1 / 3, 2 / 3, 1])
    reference = {
        (f.camera_id, f.time): f for s in ("train", "val", "test") for f in load_scene(blender, s).frames
    }
    for f in split.frames:
        ref = next(r for (c, t), r in reference.items() if c == f.camera_id and abs(t - f.time) < 1e-9)
        torch.testing.assert_close(f.camera.viewmat, ref.camera.viewmat)
        torch.testing.assert_close(f.camera.K, ref.camera.K)
        torch.testing.assert_close(load_rgba(f), load_rgba(ref))
    half = load_scene(panoptic, "train", downscale=2).frames[0]
    assert (half.width, half.height) == (12, 12)
    torch.testing.assert_close(half.camera.K[:2], split.frames[0].camera.K[:2] / 2)


def test_the_evaluation_splits_follow_the_time(scenes):
    _, panoptic = scenes
    splits = split_frames(panoptic, 0.5)
    # interpolation: the test camera up to t = 0.5; extrapolation: all four cameras at the 2 later times
    assert {(f.camera_id, round(f.time, 3)) for f in splits["interpolation"]} == {(3, 0.0), (3, 0.333)}
    assert len(splits["extrapolation"]) == 4 * 2


@pytest.mark.parametrize(
    "change, problem",
    [
        (lambda m: m.pop("w2c"), "missing w2c"),
        (lambda m: m["k"].pop(), "expected k [T][C][3][3]"),
        (lambda m: m["w2c"][0][0].pop(), "must be arrays"),
    ],
)
def test_malformed_meta_names_the_file_and_the_problem(scenes, change, problem):
    _, panoptic = scenes
    path = panoptic / "train_meta.json"
    meta = json.loads(path.read_text())
    change(meta)
    path.write_text(json.dumps(meta))
    with pytest.raises(DatasetError) as err:
        load_scene(panoptic, "train")
    assert str(path) in str(err.value) and problem in str(err.value)


def test_trains_and_evaluates_end_to_end(scenes, tmp_path):
    from tracegs.config import make_config
    from tracegs.eval.protocol import evaluate_run
    from tracegs.train.trainer import Trainer

    _, panoptic = scenes
    cfg = make_config(
        "tiny", data=panoptic, run=tmp_path / "run", device="cpu", init_points=200, t_train_end=0.5
    )
    Trainer(cfg, progress=False).train()
    result = evaluate_run(tmp_path / "run", with_lpips=False)
    assert result["interpolation"]["frames"] == 2 and result["extrapolation"]["frames"] == 8
    assert all(0 < result[s]["psnr"] < 100 for s in ("interpolation", "extrapolation"))
    written = sorted(p.name for p in (tmp_path / "run" / "eval" / "extrapolation").iterdir())
    assert written[:2] == ["c00_f002.png", "c00_f003.png"] and len(written) == 8  # one file per frame
