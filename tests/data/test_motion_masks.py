"""Motion masks of a static rig (``data/motion_masks.py``): a disc moving over a textured background,
seen by two still cameras; its masks, its cameras' plates, a camera that moves, the command."""

from __future__ import annotations

import json
import math

import imageio.v3 as iio
import numpy as np
import pytest
from scipy import ndimage

from tracegs.data.frames import DatasetError
from tracegs.data.motion_masks import (
    MotionMasks,
    MotionMaskSettings,
    background_plate,
    mask_path,
    moving_pixels,
    read_motion_mask,
    write_motion_masks,
)

SIZE, FRAMES, RADIUS = 48, 20, 6


def background(camera: int) -> np.ndarray:
    """[SIZE, SIZE, 3] a textured still scene: smooth gradients under a checkerboard."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    board = (np.floor(xx * 6) + np.floor(yy * 6)) % 2
    return np.stack(
        [0.2 + 0.3 * xx + 0.1 * board, 0.3 + 0.3 * yy + 0.1 * board, 0.4 + 0.1 * camera + 0 * xx], -1
    )


def disc(k: int, camera: int) -> np.ndarray:
    """[SIZE, SIZE] bool: where the moving disc is in frame ``k`` of ``camera``."""
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    cx = 8 + (SIZE - 16) * k / (FRAMES - 1)
    cy = 20 + 8 * camera + 4 * math.sin(k / 3)
    return (xx - cx) ** 2 + (yy - cy) ** 2 < RADIUS**2


def write_disc_scene(root, moving_camera: bool = False):
    """A Blender-layout scene folder whose split ``test`` has 2 still cameras (camera 1 turns from frame
    to frame when ``moving_camera``) filming a red disc moving over ``background``; small noise."""
    rng = np.random.default_rng(0)
    (root / "test").mkdir(parents=True)
    frames = []
    for c in range(2):
        for k in range(FRAMES):
            image = background(c) + rng.normal(0, 0.01, (SIZE, SIZE, 3))
            image[disc(k, c)] = (0.95, 0.05, 0.05)
            rel = f"test/c{c}_f{k:02d}.png"
            iio.imwrite(root / rel, (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8))
            turn = 0.05 * k if moving_camera and c == 1 else 0.0
            c2w = np.eye(4)
            c2w[:3, :3] = [
                [math.cos(turn), -math.sin(turn), 0],
                [math.sin(turn), math.cos(turn), 0],
                [0, 0, 1],
            ]
            c2w[:3, 3] = (c, 0.0, 4.0)
            frames.append(
                {"file_path": rel, "time": k / (FRAMES - 1), "camera_id": c, "transform_matrix": c2w.tolist()}
            )
    (root / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.8, "frames": frames}))
    return root


@pytest.fixture
def scene(tmp_path):
    return write_disc_scene(tmp_path / "scene")


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / (a | b).sum())


def test_the_plate_is_the_per_pixel_median():
    still = np.random.default_rng(1).random((5, 7, 3)).astype(np.float32)
    images = np.repeat(still[None], 9, axis=0)
    images[:4, 1:3, 2:5] = (1.0, 0.0, 0.0)  # something passes over some pixels in under half the frames
    images[5:9, 4, :] = 0.0
    assert np.array_equal(background_plate(images), still)


def test_the_plates_of_a_scene_are_its_background(scene):
    masks = MotionMasks.of_split(scene, "test")
    for camera in (0, 1):
        frame = next(f for f in masks.scene.frames if f.camera_id == camera)
        assert np.abs(masks.plate(frame) - background(camera)).max() < 0.02  # noise and 8 bits


@pytest.mark.parametrize("dilate", [0, 3])
def test_the_masks_match_the_moving_disc(scene, dilate):
    settings = MotionMaskSettings(dilate=dilate)
    masks = MotionMasks.of_split(scene, "test", settings=settings)
    r = np.arange(-dilate, dilate + 1)
    grow = r[:, None] ** 2 + r[None, :] ** 2 <= dilate**2
    scores = []
    for f in masks.scene.frames:
        k = int(f.image_path.stem.split("_f")[1])
        truth = (
            ndimage.binary_dilation(disc(k, f.camera_id), structure=grow) if dilate else disc(k, f.camera_id)
        )
        mask = masks.mask(f)
        assert mask.shape == (SIZE, SIZE) and mask.dtype == bool
        scores.append(iou(mask, truth))
    assert min(scores) >= 0.9, scores


def test_still_images_have_no_moving_pixels():
    image = background(0).astype(np.float32)
    noisy = image + np.random.default_rng(2).normal(0, 0.01, image.shape).astype(np.float32)
    assert not moving_pixels(noisy, image, MotionMaskSettings()).any()


def test_a_camera_of_too_few_frames_has_no_plate(scene):
    masks = MotionMasks.of_split(scene, "test", settings=MotionMaskSettings(min_frames=FRAMES + 1))
    assert all(masks.mask(f) is None for f in masks.scene.frames[:3])


def test_a_camera_that_moves_is_told_so(tmp_path):
    scene = write_disc_scene(tmp_path / "turning", moving_camera=True)
    with pytest.raises(DatasetError, match="camera 1 moves") as e:
        MotionMasks.of_split(scene, "test")
    assert str(scene) in str(e.value) and "no background plate" in str(e.value)


def test_the_masks_command_writes_one_png_per_frame(scene, tmp_path, capsys):
    from tracegs.cli import run_command

    out, figure = tmp_path / "masks", tmp_path / "figure.png"
    run_command("masks", ["--data", str(scene), "--out", str(out), "--figure", str(figure)])
    assert "40 masks in" in capsys.readouterr().out
    masks = MotionMasks.of_split(scene, "test")
    for f in masks.scene.frames[::7]:
        path = out / mask_path(scene, f)
        assert path.relative_to(out).as_posix() == f"test/{f.image_path.stem}.png"
        assert np.array_equal(iio.imread(path) == 255, masks.mask(f))
    assert len(list(out.rglob("*.png"))) == 2 * FRAMES and not list(out.rglob("*.tmp"))
    frame = masks.scene.frames[3]
    assert np.array_equal(read_motion_mask(out / mask_path(scene, frame), frame), masks.mask(frame))
    assert iio.imread(figure).shape == (2 * SIZE + 2, 5 * SIZE + 8, 3)


def test_the_report_says_which_cameras_have_no_plate(scene, tmp_path):
    settings = MotionMaskSettings(min_frames=FRAMES + 1)
    report = write_motion_masks(scene, "test", tmp_path / "none", settings=settings)
    assert report["written"] == 0 and all(c["plate"] is None for c in report["cameras"])


def test_a_mask_file_of_another_size_is_an_error_naming_it(scene, tmp_path):
    frame = MotionMasks.of_split(scene, "test").scene.frames[0]
    wrong = tmp_path / "wrong.png"
    iio.imwrite(wrong, np.zeros((SIZE, SIZE + 5), np.uint8))
    with pytest.raises(
        DatasetError, match=f"{wrong}: mask of {SIZE + 5}x{SIZE} for an image of {SIZE}x{SIZE}"
    ):
        read_motion_mask(wrong, frame)
    with pytest.raises(DatasetError, match="missing.png: no motion mask"):
        read_motion_mask(tmp_path / "missing.png", frame)


def test_the_command_says_in_one_line_that_the_cameras_move(tmp_path, capsys):
    from tracegs.cli import main

    scene = write_disc_scene(tmp_path / "turning", moving_camera=True)
    with pytest.raises(SystemExit) as e:
        main(["masks", "--data", str(scene), "--out", str(tmp_path / "masks")])
    err = capsys.readouterr().err.strip()
    assert e.value.code == 1 and len(err.splitlines()) == 1
    assert err.startswith("tracegs masks: error: ") and "camera 1 moves" in err
    assert not (tmp_path / "masks").exists()
