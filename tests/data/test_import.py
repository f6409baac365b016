"""``tracegs import``: the undistortion against a known camera model, the similarity transforms, an
import from a calibration file (the layout, the report, the masks, bad input, nothing half-written),
and the COLMAP path on a small synthetic rig."""

from __future__ import annotations

import json
import math
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

pycolmap = pytest.importorskip("pycolmap")
pytest.importorskip("av")

from tracegs.data.calibration import align_cameras, centres_of, normalise, transform_w2c, umeyama  # noqa: E402
from tracegs.data.colmap import largest_shift, undistort, undistortion_map  # noqa: E402
from tracegs.data.frames import DatasetError  # noqa: E402
from tracegs.data.importer import import_scene  # noqa: E402
from tracegs.data.scene import load_scene  # noqa: E402


def _rotation(rng) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


def _ring(n: int, radius: float = 3.0, height: float = 1.0) -> np.ndarray:
    """[n, 4, 4] OpenCV world-to-camera of cameras on a ring about the z axis, looking at the origin."""
    out = []
    for k in range(n):
        a = 2 * math.pi * k / n
        eye = np.array([radius * math.cos(a), radius * math.sin(a), height])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        R = np.stack([right, np.cross(forward, right), forward])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = R, -R @ eye
        out.append(w2c)
    return np.stack(out)


def test_undistortion_against_a_known_model():
    """An image of a pattern seen through a known radial distortion, undistorted, is the pattern seen
    through the pinhole camera (up to the bilinear resampling)."""
    W, H, f = 96, 64, 80.0
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=W, height=H, params=[f, W / 2, H / 2, -0.15])
    pattern = lambda x, y: 127.5 + 100 * np.sin(9 * x) * np.cos(7 * y)  # noqa: E731  (normalised coords)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xy = camera.cam_from_img(np.stack([u.ravel(), v.ravel()], -1)).reshape(H, W, 2)
    distorted = np.repeat(pattern(xy[..., 0], xy[..., 1])[..., None], 3, -1)
    K = np.array([[f, 0, W / 2], [0, f, H / 2], [0, 0, 1]])
    coords = undistortion_map(camera, K, W, H)
    assert largest_shift(coords) > 2  # the model moves the corners by pixels
    out = undistort(distorted.astype(np.float32), coords)[..., 0]
    expected = pattern((u - W / 2) / f, (v - H / 2) / f)
    inner = (slice(8, -8), slice(8, -8))
    after = np.abs(out - expected)[inner].max()
    assert after < 6  # of an amplitude of 100
    assert np.abs(distorted[..., 0] - expected)[inner].max() > 2 * after  # it was farther before


def test_umeyama_and_alignment_recover_a_similarity():
    rng = np.random.default_rng(0)
    truth = _ring(6)
    s, R, t = 0.37, _rotation(rng), rng.normal(size=3)
    moved = transform_w2c(truth, s, R, t)
    assert np.allclose(centres_of(moved), s * centres_of(truth) @ R.T + t)
    s2, R2, t2 = umeyama(centres_of(moved), centres_of(truth))
    assert math.isclose(s2, 1 / s, rel_tol=1e-9) and np.allclose(R2, R.T)
    report = align_cameras(moved, truth)
    assert report["centre_error_max"] < 1e-9 and report["direction_error_max_deg"] < 1e-4
    tilted = moved.copy()
    tilted[0, :3, :3] = _rotation(rng) @ tilted[0, :3, :3]  # one camera looks elsewhere
    assert align_cameras(tilted, truth)["direction_error_max_deg"] > 1


def test_normalise_centres_the_rig_with_up_along_z():
    rng = np.random.default_rng(1)
    rig = transform_w2c(_ring(8, radius=2.0, height=0.0), 3.0, _rotation(rng), rng.normal(size=3))
    s, R, t, note = normalise(rig, distance=4.0)
    placed = transform_w2c(rig, s, R, t)
    assert np.allclose(np.linalg.norm(centres_of(placed), axis=1), 4.0)
    assert np.allclose(-placed[:, 1, :3].mean(0) / np.linalg.norm(placed[:, 1, :3].mean(0)), [0, 0, 1])
    assert note["centre"] == "the point the cameras look at"


# ----- an import from a calibration file ----------------------------------------------------------
def _rig_folders(root: Path, cameras: int = 3, frames: int = 12, size: int = 32) -> Path:
    """Folders of frames: a textured still background, a bright square crossing it."""
    rng = np.random.default_rng(2)
    for c in range(cameras):
        (root / f"cam{c}").mkdir(parents=True)
        plate = rng.integers(0, 120, (size, size, 3), dtype=np.uint8)
        for k in range(frames):
            image = plate.copy()
            x = 2 + 2 * k
            image[10:18, x : x + 8] = 255
            iio.imwrite(root / f"cam{c}" / f"{k:04d}.png", image)
    return root


def _nerfstudio(path: Path, w2c: np.ndarray, names: list[str], size: int, k1: float = 0.0) -> Path:
    frames = []
    for name, m in zip(names, w2c, strict=True):
        c2w = np.linalg.inv(m)
        c2w[:3, 1:3] *= -1
        frames.append({"file_path": f"images/{name}/0000.png", "transform_matrix": c2w.tolist()})
    top = {"fl_x": 40.0, "fl_y": 40.0, "cx": size / 2, "cy": size / 2, "w": size, "h": size, "k1": k1}
    path.write_text(json.dumps(top | {"frames": frames}))
    return path


def test_import_from_a_calibration_file(tmp_path):
    frames = _rig_folders(tmp_path / "rig")
    w2c = _ring(3)
    calibration = _nerfstudio(tmp_path / "transforms.json", w2c, ["cam0", "cam1", "cam2"], 64)
    out = tmp_path / "scene"
    report = import_scene(
        out, images=frames, calibration=calibration, test_cameras=("cam2",), log=lambda s: None
    )
    assert report["registered"] == ["cam0", "cam1", "cam2"] and report["dropped"] == {}
    assert report["splits"] == {"train": ["cam0", "cam1"], "test": ["cam2"]}
    train, test = load_scene(out, "train"), load_scene(out, "test")
    assert len(train.frames) == 24 and len(test.frames) == 12
    assert sorted({f.time for f in train.frames}) == pytest.approx([k / 11 for k in range(12)])
    f = test.frames[0]
    assert f.image_path.parent.name == "cam2" and f.camera_id == 2
    assert np.allclose(f.camera.viewmat.numpy(), w2c[2], atol=1e-5)  # a file's world is kept
    assert np.allclose(f.camera.K.numpy()[0, 0], 20.0)  # 40 px at 64 px wide -> 20 at 32
    entry = json.loads((out / "transforms_test.json").read_text())["frames"][0]
    assert entry["camera"] == "cam2"
    assert json.loads((out / "import.json").read_text())["splits"] == report["splits"]
    mask = iio.imread(out / "masks" / "images" / "cam0" / "cam0_f00005.png")
    assert mask[12, 14] > 0 and mask[28, 2] == 0  # the square moves, the background does not
    assert report["masks"]["train"]["written"] == 24


def test_a_camera_without_calibration_is_named_or_dropped(tmp_path):
    frames = _rig_folders(tmp_path / "rig")
    calibration = _nerfstudio(tmp_path / "transforms.json", _ring(2), ["cam0", "cam1"], 32)
    out = tmp_path / "scene"
    with pytest.raises(DatasetError, match=r"cam2: camera cam2 has no calibration .*--drop-unregistered"):
        import_scene(out, images=frames, calibration=calibration, log=lambda s: None)
    assert not out.exists() and list(tmp_path.iterdir()) == sorted(tmp_path.iterdir())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig", "transforms.json"]  # nothing half-written
    report = import_scene(
        out, images=frames, calibration=calibration, drop_unregistered=True, log=lambda s: None
    )
    assert report["registered"] == ["cam0", "cam1"] and "cam2" in report["dropped"]
    assert not (out / "images" / "cam2").exists()


def test_a_distorted_calibration_is_undistorted(tmp_path):
    frames = _rig_folders(tmp_path / "rig", frames=3)
    calibration = _nerfstudio(tmp_path / "t.json", _ring(3), ["cam0", "cam1", "cam2"], 32, k1=-0.2)
    report = import_scene(tmp_path / "scene", images=frames, calibration=calibration, log=lambda s: None)
    assert all(v.startswith("undistorted (OPENCV") for v in report["undistortion"].values())
    with pytest.raises(ValueError, match="--test-cameras cam7: no such camera"):
        import_scene(tmp_path / "other", images=frames, calibration=calibration, test_cameras=("cam7",))


def test_an_existing_folder_is_not_overwritten(tmp_path):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "mine.txt").write_text("keep")
    frames = _rig_folders(tmp_path / "rig", frames=2)
    with pytest.raises(FileExistsError, match="did not write"):
        import_scene(tmp_path / "scene", images=frames, calibration=tmp_path / "t.json")


def test_the_command_writes_the_scene_and_says_a_bad_input_in_one_line(tmp_path, capsys):
    from tracegs.cli import main

    frames = _rig_folders(tmp_path / "rig", frames=3)
    calibration = _nerfstudio(tmp_path / "t.json", _ring(3), ["cam0", "cam1", "cam2"], 32)
    args = [
        "import",
        "--images",
        str(frames),
        "--calibration",
        str(calibration),
        "--out",
        str(tmp_path / "s"),
    ]
    main([*args, "--val-cameras", "cam1", "--json", str(tmp_path / "r.json")])
    out = capsys.readouterr().out
    assert "3 cameras calibrated" in out and "train: 2 cameras, val: 1 camera" in out
    assert json.loads((tmp_path / "r.json").read_text())["splits"]["val"] == ["cam1"]
    (tmp_path / "rig" / "cam3").mkdir()
    with pytest.raises(SystemExit) as exit_:
        main(args)
    err = capsys.readouterr().err.strip()
    assert (
        exit_.value.code == 1
        and "\n" not in err
        and err.endswith("cam3: no frames (PNG or JPEG files) in the camera's folder")
    )


def test_a_dynamic_3d_gaussians_meta_and_a_rescaled_distorted_camera(tmp_path):
    frames = _rig_folders(tmp_path / "rig", frames=2)
    w2c = _ring(3)
    K = [[[40.0, 0, 32], [0, 40.0, 32], [0, 0, 1]]] * 3
    meta = {"w": 64, "h": 64, "k": [K], "w2c": [w2c.tolist()], "cam_id": [[0, 1, 2]]}
    meta["fn"] = [[f"cam{c}/000000.jpg" for c in range(3)]]
    (tmp_path / "train_meta.json").write_text(json.dumps(meta))
    report = import_scene(
        tmp_path / "a", images=frames, calibration=tmp_path / "train_meta.json", log=lambda s: None
    )
    scene = load_scene(tmp_path / "a", "train")
    assert report["registered"] == ["cam0", "cam1", "cam2"]
    assert np.allclose(scene.frames[1].camera.viewmat.numpy(), w2c[1], atol=1e-5)
    assert np.allclose(scene.frames[1].camera.K.numpy()[:2, :3], [[20, 0, 16], [0, 20, 16]])
    calibration = _nerfstudio(tmp_path / "t.json", w2c, ["cam0", "cam1", "cam2"], 64, k1=-0.2)
    report = import_scene(tmp_path / "b", images=frames, calibration=calibration, log=lambda s: None)
    assert all(v.startswith("undistorted (OPENCV") for v in report["undistortion"].values())
    assert np.allclose(load_scene(tmp_path / "b", "train").frames[0].camera.K.numpy()[0, 0], 20.0)
