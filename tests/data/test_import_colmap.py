"""The COLMAP path of ``tracegs import`` on a small synthetic rig, where the truth is known: a ``tracegs
synth`` scene with textured surroundings as one MP4 per camera, plus a camera that films noise (which
nothing ties to the rig), imported without poses; the recovered cameras aligned to the true ones. And
what ``--textured-surroundings`` changes in a synthetic scene (the background only).

The targets of the closed loop (1% of the rig's radius, 0.5 degrees) are for rigs of larger images
(``benchmarks/import_closed_loop.py``); this rig of 320-pixel images is small enough for a test and held to 2% and 0.75 degrees.
"""

from __future__ import annotations

import imageio.v3 as iio
import numpy as np
import pytest

pytest.importorskip("pycolmap")
pytest.importorskip("av")
pytest.importorskip("mitsuba")

from tracegs.data.calibration import align_cameras  # noqa: E402
from tracegs.data.importer import import_scene  # noqa: E402
from tracegs.data.scene import load_scene  # noqa: E402
from tracegs.data.synth import synthesize  # noqa: E402
from tracegs.data.synth.videos import imported_w2c, true_w2c, write_rig_videos  # noqa: E402
from tracegs.data.video import write_video  # noqa: E402

RES, VIEWS, FRAMES = 320, 10, 2


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    root = tmp_path_factory.mktemp("loop")
    scene = synthesize(
        "fan", root / "synth", RES, VIEWS, FRAMES, progress=False, spp=4, textured_surroundings=True
    )
    write_rig_videos(scene, root / "videos")
    noise = np.random.default_rng(0).integers(0, 256, (FRAMES, RES, RES, 3), dtype=np.uint8)
    write_video(root / "videos" / "noise.mp4", noise, 30.0)
    report = import_scene(
        root / "imported", videos=root / "videos", test_cameras=("c09",), drop_unregistered=True,
        log=lambda s: None,
    )  # fmt: skip
    return scene, root / "imported", report


def test_every_camera_of_the_rig_is_recovered(imported):
    scene, out, report = imported
    truth, found = true_w2c(scene), imported_w2c(out)
    assert sorted(found) == sorted(truth) == report["registered"]
    names = sorted(truth)
    errors = align_cameras(np.stack([found[n] for n in names]), np.stack([truth[n] for n in names]))
    assert errors["centre_error_max"] < 0.02, errors
    assert errors["direction_error_max_deg"] < 0.75, errors
    assert report["calibration"]["mean_reprojection_error_px"] < 1.5


def test_the_camera_that_films_noise_is_dropped_and_said(imported):
    _, out, report = imported
    assert list(report["dropped"]) == ["noise"] and "features" in report["dropped"]["noise"]
    assert not (out / "images" / "noise").exists()
    assert report["calibration"]["per_camera"]["noise"]["registered"] is False


def test_the_imported_scene_is_read_as_any_scene(imported):
    _, out, report = imported
    train, test = load_scene(out, "train"), load_scene(out, "test")
    assert len(train.frames) == (VIEWS - 1) * FRAMES and {f.image_path.parent.name for f in test.frames} == {
        "c09"
    }
    assert sorted({f.time for f in train.frames}) == [0.0, 1.0]
    centres = np.stack([f.camera.center.numpy() for f in train.frames])
    assert np.allclose(np.median(np.linalg.norm(centres, axis=1)), 4.0, rtol=0.05)  # round the origin
    up = np.mean([-f.camera.viewmat[1, :3].numpy() for f in train.frames], axis=0)
    assert up[2] / np.linalg.norm(up) > 0.99
    assert (out / "colmap" / "sparse" / "0").is_dir() and not (out / "colmap" / "database.db").exists()


def test_textured_surroundings_fill_the_background_and_leave_the_masks(tmp_path):
    args = {"resolution": 24, "views": 2, "frames": 2, "progress": False, "spp": 1}
    plain = synthesize("fan", tmp_path / "plain", **args)
    room = synthesize("fan", tmp_path / "room", **args, textured_surroundings=True)
    for image in sorted((plain / "train").glob("*.png")):
        before, after = iio.imread(image), iio.imread(room / "train" / image.name)
        assert before[..., 3].min() == 0 and after[..., 3].min() == 255  # the room fills what was empty
        covered = before[..., 3] == 255
        assert np.abs(after[covered].astype(int) - before[covered]).mean() < 20  # the object as it was
        masks = [iio.imread(d / "gt" / "masks" / "train" / image.name) for d in (plain, room)]
        assert np.array_equal(*masks)


def test_the_written_colmap_model_is_a_calibration_that_gives_the_same_scene(imported, tmp_path):
    _, out, _ = imported
    again = tmp_path / "again"
    report = import_scene(
        again, videos=out.parent / "videos", calibration=out / "colmap" / "sparse" / "0",
        test_cameras=("c09",), drop_unregistered=True, log=lambda s: None,
    )  # fmt: skip
    assert report["calibration"]["tool"] == "COLMAP model" and list(report["dropped"]) == ["noise"]
    first, second = imported_w2c(out), imported_w2c(again)
    assert sorted(first) == sorted(second)
    assert all(np.allclose(first[n], second[n], atol=1e-6) for n in first)
