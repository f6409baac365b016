"""The Blender/D-NeRF parser on a generated scene and on malformed files."""

import json
import math
from pathlib import Path

import pytest
import torch

from tracegs.data.cameras import focus_point, look_at_viewmat, opengl_c2w_to_viewmat
from tracegs.data.scene import DatasetError, load_image, load_rgba, load_scene


def test_parses_tiny_scene(tiny_scene):
    scene = load_scene(tiny_scene, "train")
    assert len(scene.frames) == 3 * 4 - 3  # 3 training cameras x 3 times <= 0.75
    f = scene.frames[0]
    assert (f.width, f.height) == (24, 24)
    assert f.time == 0.0
    fx = 0.5 * 24 / math.tan(0.35)
    assert torch.allclose(f.camera.K, torch.tensor([[fx, 0, 12], [0, fx, 12], [0, 0, 1.0]]))
    assert scene.fps == 3 and scene.t_train_end == 0.75
    img = load_image(f, scene.background)
    assert img.shape == (24, 24, 3) and 0 <= img.min() and img.max() <= 1
    # transparent corner composited on the white background
    assert torch.allclose(img[0, 0], torch.ones(3))


def test_camera_convention_looks_at_origin(tiny_scene):
    # every generated camera looks at the origin: it must project to the image centre, in front
    for f in load_scene(tiny_scene, "test").frames:
        p = f.camera.viewmat @ torch.tensor([0.0, 0, 0, 1])
        assert p[2] > 0
        uv = (f.camera.K @ p[:3])[:2] / p[2]
        assert torch.allclose(uv, torch.tensor([12.0, 12.0]), atol=1e-3)


def test_opengl_conversion_matches_look_at():
    eye = torch.tensor([2.0, -1.0, 1.5])
    viewmat = look_at_viewmat(eye, (0, 0, 0), (0, 0, 1))
    c2w_cv = torch.linalg.inv(viewmat)
    c2w_gl = c2w_cv.clone()
    c2w_gl[:3, 1:3] *= -1
    assert torch.allclose(opengl_c2w_to_viewmat(c2w_gl), viewmat, atol=1e-5)


def test_downscale_halves_intrinsics_and_images(tiny_scene):
    full, half = load_scene(tiny_scene, "train"), load_scene(tiny_scene, "train", downscale=2)
    assert half.frames[0].width == 12
    assert torch.allclose(half.frames[0].camera.K[:2], full.frames[0].camera.K[:2] / 2)
    assert load_image(half.frames[0]).shape == (12, 12, 3)


@pytest.mark.parametrize(
    "content, problem",
    [
        ("{not json", "not valid JSON"),
        (json.dumps({"camera_angle_x": 0.5}), "non-empty list 'frames'"),
        (json.dumps({"camera_angle_x": 0.5, "frames": [{"file_path": "x"}]}), "transform_matrix"),
        (
            json.dumps(
                {"camera_angle_x": 0.5, "frames": [{"file_path": "x", "transform_matrix": [[1, 0], [0, 1]]}]}
            ),
            "4x4",
        ),
    ],
)
def test_malformed_json_names_file(tmp_path, content, problem):
    path = tmp_path / "transforms_train.json"
    path.write_text(content)
    with pytest.raises(DatasetError) as err:
        load_scene(tmp_path, "train")
    assert str(path) in str(err.value) and problem in str(err.value)


def test_missing_file_and_missing_intrinsics(tiny_scene, tmp_path):
    with pytest.raises(DatasetError, match="file not found"):
        load_scene(tmp_path, "train")
    meta = json.loads((tiny_scene / "transforms_train.json").read_text())
    del meta["camera_angle_x"]
    (tiny_scene / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match="no intrinsics"):
        load_scene(tiny_scene, "train")


def test_corrupt_image_names_file(tiny_scene):
    scene = load_scene(tiny_scene, "train")
    scene.frames[1].image_path.write_bytes(b"not a png")
    with pytest.raises(DatasetError, match=str(scene.frames[1].image_path.name)):
        load_image(scene.frames[1])


def _ring(center, radius, n=8, elevation=0.5):
    """World-to-camera matrices of ``n`` cameras on a ring around ``center``, all looking at it."""
    center = torch.as_tensor(center, dtype=torch.float32)
    eyes = [
        center
        + radius
        * torch.tensor(
            [math.cos(a) * math.cos(elevation), math.sin(a) * math.cos(elevation), math.sin(elevation)]
        )
        for a in (2 * math.pi * k / n for k in range(n))
    ]
    return torch.stack([look_at_viewmat(eye, center) for eye in eyes])


def test_focus_point_is_where_the_cameras_look():
    point = focus_point(_ring((2.0, -1.0, 5.0), 30.0))
    assert point is not None and torch.allclose(
        point, torch.tensor([2.0, -1.0, 5.0], dtype=torch.float64), atol=1e-4
    )


def test_focus_point_refuses_parallel_or_backward_axes():
    eyes = [(x, 0.0, 0.0) for x in (-1.0, 0.0, 1.0)]
    forward = torch.stack([look_at_viewmat(e, (e[0], 10.0, 0.0)) for e in eyes])  # forward-facing capture
    assert focus_point(forward) is None
    inward = _ring((0.0, 0.0, 0.0), 4.0)
    outward = inward.clone()
    outward[:, 2, :] *= -1  # flip each camera's forward axis (and its y axis, to stay a rotation)
    outward[:, 1, :] *= -1
    assert focus_point(outward) is None


def test_training_times_outside_unit_interval_are_refused(tiny_scene):
    """Frame indices written as times would make every time look alike to the fields' encodings."""
    path = tiny_scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    for k, f in enumerate(meta["frames"]):
        f["time"] = float(k)
    path.write_text(json.dumps(meta))
    with pytest.raises(DatasetError, match=r"'time' 2 is outside \[0, 1\]") as err:
        load_scene(tiny_scene, "train")
    assert str(path) in str(err.value)


def test_file_path_without_suffix_finds_a_jpg(tiny_scene):
    """D-NeRF writes ``./train/r_000``; the image may be a PNG or, in converted captures, a JPEG."""
    import imageio.v3 as iio

    path = tiny_scene / "transforms_train.json"
    meta = json.loads(path.read_text())
    first = meta["frames"][0]
    png = tiny_scene / first["file_path"]
    jpg = png.with_suffix(".jpg")
    iio.imwrite(jpg, iio.imread(png)[..., :3])
    png.unlink()
    first["file_path"] = "./" + str(Path(first["file_path"]).with_suffix(""))
    path.write_text(json.dumps(meta))
    frame = load_scene(tiny_scene, "train").frames[0]
    assert frame.image_path == jpg.resolve()
    assert load_rgba(frame).shape[-1] == 4
