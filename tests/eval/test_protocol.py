"""The evaluation protocol: split membership, the JSON schema, per-time rows; render and metrics CLI."""

import json
import math
from pathlib import Path

import pytest
from tests.conftest import write_tiny_scene

from tracegs.cli import main
from tracegs.config import make_config
from tracegs.eval.protocol import evaluate_run, split_frames
from tracegs.train.trainer import Trainer

FIELDS = {"psnr", "mae_psnr", "ssim", "lpips_vgg", "lpips_alex", "frames"}


@pytest.fixture(scope="module")
def trained_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    scene = write_tiny_scene(root / "scene", n_cams=3, n_times=5, size=32)
    cfg = make_config("tiny", data=scene, run=root / "run", device="cpu")
    Trainer(cfg, progress=False).train()
    return scene, root / "run"


def test_splits_follow_the_protocol(trained_run):
    scene, _ = trained_run
    splits = split_frames(scene, t_train_end=0.75)
    assert splits["extrapolation"] and all(f.time > 0.75 for f in splits["extrapolation"])
    assert len(splits["extrapolation"]) == 3  # every camera at t = 1.0
    assert splits["interpolation"] and all(f.time <= 0.75 for f in splits["interpolation"])
    assert {f.camera_id for f in splits["interpolation"]} == {2}  # the held-out camera only


def test_validation_future_holds_only_later_training_frames(trained_run):
    scene, _ = trained_run
    splits = split_frames(scene, t_train_end=0.5, future_end=0.75, with_cameras=True)
    future = splits["extrapolation"]
    # the training cameras (0, 1) at the one training time after the cut; no test frame (t = 1.0)
    assert sorted((f.camera_id, f.time) for _, f in future) == [(0, 0.75), (1, 0.75)]
    assert {c for c, _ in future} == {"train_cameras"}
    assert sorted(f.time for _, f in splits["interpolation"]) == [0.0, 0.25, 0.5]


def test_held_out_frames_in_the_training_span_count_as_interpolation(tmp_path):
    # D-NeRF layout: no val split, and a test split spread over the whole time range. Its frames at
    # t <= t_train_end are interpolation; the validation future never looks at a test frame.
    scene = write_tiny_scene(tmp_path / "scene", n_cams=3, n_times=5, size=16)
    val, test = (json.loads((scene / f"transforms_{s}.json").read_text()) for s in ("val", "test"))
    test["frames"] += val["frames"]
    (scene / "transforms_test.json").write_text(json.dumps(test))
    (scene / "transforms_val.json").unlink()
    splits = split_frames(scene, t_train_end=0.75)
    assert sorted((f.camera_id, f.time) for f in splits["interpolation"]) == [
        (2, 0.0),
        (2, 0.25),
        (2, 0.5),
        (2, 0.75),
    ]
    assert len(splits["extrapolation"]) == 3
    validation = split_frames(scene, t_train_end=0.5, future_end=0.75)
    assert validation["interpolation"] == [] and {f.time for f in validation["extrapolation"]} == {0.75}


def test_eval_json_has_every_field(trained_run, tmp_path, capsys):
    pytest.importorskip("tracegs.eval.lpips")
    _, run = trained_run
    out = tmp_path / "eval.json"
    main(["eval", "--run", str(run), "--json", str(out)])
    result = json.loads(out.read_text())
    # the console gets a summary whose numbers are the file's
    printed = capsys.readouterr().out
    extrap = result["extrapolation"]
    assert f"{extrap['mae_psnr']:.2f}" in printed and f"{extrap['ssim']:.4f}" in printed
    assert str(out) in printed
    assert FIELDS <= set(result["interpolation"]) and FIELDS <= set(result["extrapolation"])
    for key in ("method", "preset", "scene", "train_seconds", "iterations", "gaussians"):
        assert key in result
    rows = result["extrapolation"]["per_time"]
    assert [r["t"] for r in rows] == [1.0] and {"t", "psnr", "ssim", "lpips_vgg"} <= set(rows[0])
    assert result["interpolation"]["frames"] == 4 and result["extrapolation"]["frames"] == 3
    # one time in the extrapolation split: its row is the split's MAE-PSNR
    assert rows[0]["psnr"] == pytest.approx(result["extrapolation"]["mae_psnr"])
    # per camera set: 2 training cameras + 1 held-out camera, together the whole split
    per = result["extrapolation"]["per_cameras"]
    assert {k: v["frames"] for k, v in per.items()} == {"train_cameras": 2, "new_cameras": 1}
    pooled = sum(v["frames"] * 10 ** (-v["mae_psnr"] / 10) for v in per.values()) / 3
    assert -10 * math.log10(pooled) == pytest.approx(result["extrapolation"]["mae_psnr"], abs=1e-6)


def test_half_resolution_scoring(trained_run):
    _, run = trained_run
    result = evaluate_run(run, half_res=True, with_lpips=False, save_images=False, device="cpu")
    assert result["extrapolation"]["frames"] == 3 and "lpips_vgg" not in result["extrapolation"]


def test_render_future_time_and_video(trained_run, tmp_path):
    import imageio.v3 as iio

    _, run = trained_run
    out = tmp_path / "future.png"
    main(["render", "--run", str(run), "--time", "1.4", "--camera", "val:0", "--out", str(out)])
    assert iio.imread(out).shape == (32, 32, 3)
    main(["render", "--run", str(run), "--camera", "orbit:45", "--out", str(tmp_path / "orbit.png")])
    assert iio.imread(tmp_path / "orbit.png").shape == (32, 32, 3)
    video = tmp_path / "sweep.mp4"
    main(["render", "--run", str(run), "--video", "--frames", "4", "--out", str(video)])
    assert video.exists() or video.with_suffix(".gif").exists()


def test_metrics_command(tmp_path, capsys):
    import imageio.v3 as iio
    import numpy as np

    a = np.zeros((40, 40, 3), np.uint8)
    b = a.copy()
    b[:] = 26  # 26/255 offset: MSE = (26/255)^2
    iio.imwrite(tmp_path / "a.png", a)
    iio.imwrite(tmp_path / "b.png", b)
    main(["metrics", str(tmp_path / "a.png"), str(tmp_path / "b.png"), "--json", str(tmp_path / "m.json")])
    m = json.loads((tmp_path / "m.json").read_text())
    assert m["psnr"] == pytest.approx(-10 * np.log10((26 / 255) ** 2), abs=1e-4)


def test_part_errors_split_the_squared_error_by_mask(tmp_path):
    import imageio.v3 as iio
    import numpy as np
    import torch

    from tracegs.eval.protocol import PartErrors

    ids = np.zeros((4, 4), dtype=np.uint8)
    ids[:, 2:] = 2  # left half background, right half part 2; part 1 absent
    iio.imwrite(tmp_path / "m.png", ids)
    gt = torch.zeros(4, 4, 3)
    pred = gt.clone()
    pred[:, :2] = 0.1  # background error 0.01 per pixel
    pred[:, 2:] = 0.3  # part error 0.09 per pixel
    parts = PartErrors({0: "background", 1: "body", 2: "blades"})
    parts.add(pred, gt, tmp_path / "m.png")
    parts.add(pred, gt, tmp_path / "missing.png")  # no mask: skipped
    out = parts.summary()
    assert set(out) == {"background", "blades"}
    assert out["blades"]["pixel_share"] == pytest.approx(0.5)
    assert out["blades"]["error_share"] == pytest.approx(0.9)
    assert out["background"]["error_share"] == pytest.approx(0.1)
    assert out["blades"]["psnr"] == pytest.approx(-10 * math.log10(0.09))
    with pytest.raises(ValueError, match="m.png"):
        parts.add(pred[:2], gt[:2], tmp_path / "m.png")


def test_console_summary_reports_parts_and_physics():
    from tracegs.eval.report import format_summary

    split = {"frames": 2, "psnr": 30.0, "mae_psnr": 29.5, "ssim": 0.95}
    result = {
        "interpolation": split,
        "extrapolation": split
        | {
            "per_time": [{"t": 0.8, "psnr": 31.0}, {"t": 1.0, "psnr": 28.0}],
            "per_part": {"blades": {"psnr": 21.0, "pixel_share": 0.1, "error_share": 0.5}},
        },
        "physics": {
            "parts": {
                "2": {
                    "mean_trajectory_error": 0.004,
                    "omega_learned": [0, 0, 1.9],
                    "omega_gt": [0, 0, 2.0],
                    "omega_rel_error": 0.05,
                    "axis_error_deg": 0.1,
                }
            }
        },
        "method": "trace",
        "t_train_end": 0.75,
    }
    text = format_summary(result)
    assert "t=1.000 28.00 dB" in text and "blades 21.00 dB (10% of pixels, 50% of error)" in text
    assert "|w| 1.900 vs 2.000 (5.0%)" in text and "axis off by 0.10 deg" in text
    assert "LPIPS" not in text  # columns the result lacks are left out


def _scene_copy(trained_run, tmp_path):
    import shutil

    return shutil.copytree(trained_run[0], tmp_path / "scene")


def test_val_and_test_frames_of_one_name_are_written_apart(trained_run, tmp_path):
    """D-NeRF names its images r_000 in each split: one interpolation split must keep both."""
    import shutil

    import imageio.v3 as iio

    scene = _scene_copy(trained_run, tmp_path)
    val = json.loads((scene / "transforms_val.json").read_text())
    test = json.loads((scene / "transforms_test.json").read_text())
    twin = dict(val["frames"][0], file_path="test/" + val["frames"][0]["file_path"].split("/")[1])
    twin["transform_matrix"] = test["frames"][0]["transform_matrix"]  # another camera, same name
    shutil.copy(scene / val["frames"][0]["file_path"], scene / twin["file_path"])
    test["frames"].append(twin)
    (scene / "transforms_test.json").write_text(json.dumps(test))
    out = tmp_path / "images"
    result = evaluate_run(trained_run[1], scene, with_lpips=False, device="cpu", out=out)
    written = sorted(p.name for p in (out / "interpolation").iterdir())
    name = Path(twin["file_path"]).stem
    assert f"val_{name}.png" in written and f"test_{name}.png" in written and f"{name}.png" not in written
    assert len(written) == result["interpolation"]["frames"]
    a, b = (iio.imread(out / "interpolation" / f"{s}_{name}.png") for s in ("val", "test"))
    assert (a != b).any()  # two cameras' renders, neither overwritten by the other


def test_eval_writes_its_images_into_out(trained_run, tmp_path, capsys):
    _, run = trained_run
    out, path = tmp_path / "frames", tmp_path / "e.json"
    main(["eval", "--run", str(run), "--out", str(out), "--json", str(path), "--no-lpips"])
    result = json.loads(path.read_text())
    for split in ("interpolation", "extrapolation"):
        assert len(list((out / split).glob("*.png"))) == result[split]["frames"] > 0
    assert result["images"] == str(out)


def _synth_motion(gt):
    from tracegs.data.synth.motion import RigidMotion, motion_record

    parts = [motion_record("disc", 1, RigidMotion("rotation", angular_velocity=1.0))]
    (gt / "motion.json").write_text(json.dumps({"parts": parts}))


def _synth_points(gt, **keys):
    import numpy as np

    keys = keys or {"points": np.zeros((10, 3)), "part_ids": np.ones(10, dtype=np.int64)}
    np.savez(gt / "points.npz", **keys)


GT_LAYOUTS = {
    # name: (files written into gt/, what the notes must say; None: nothing skipped but per-part errors)
    "tracegs synth": ((_synth_motion, _synth_points), None),
    "another motion format": (
        (lambda gt: (gt / "motion.json").write_text('{"objects": []}'), _synth_points),
        "motion.json",
    ),
    "no points.npz": ((_synth_motion,), "points.npz not found"),
    "points.npz with other keys": (
        (_synth_motion, lambda gt: _synth_points(gt, xyz=__import__("numpy").zeros((4, 3)))),
        "points.npz",
    ),
    "points.npz not an archive": (
        (_synth_motion, lambda gt: (gt / "points.npz").write_bytes(b"xx")),
        "points.npz",
    ),
}


@pytest.mark.parametrize("writers, skipped", GT_LAYOUTS.values(), ids=list(GT_LAYOUTS))
def test_ground_truth_of_another_layout_is_skipped_and_said(trained_run, tmp_path, capsys, writers, skipped):
    scene = _scene_copy(trained_run, tmp_path)
    (scene / "gt").mkdir()
    for write in writers:
        write(scene / "gt")
    path = tmp_path / "e.json"
    main(["eval", "--run", str(trained_run[1]), "--data", str(scene), "--json", str(path), "--no-lpips"])
    result = json.loads(path.read_text())
    printed = capsys.readouterr().out
    physics_notes = [n for n in result.get("notes", []) if n.startswith("physics errors skipped")]
    assert result["extrapolation"]["frames"] > 0
    if skipped is None:
        assert "physics" in result and not physics_notes
    else:
        assert "physics" not in result and len(physics_notes) == 1 and skipped in physics_notes[0]
        assert f"note: {physics_notes[0]}" in printed
    assert any("per-part errors skipped: no masks" in n for n in result["notes"])  # no gt/masks here
