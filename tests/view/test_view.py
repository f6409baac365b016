"""The viewer (``tracegs view``): the browser's camera as ours, the time -> geometry it shows, and the
web server serving viser's page for a run."""

from __future__ import annotations

import math
import shutil
import socket
import urllib.request
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import write_tiny_scene
from tracegs.data.cameras import look_at_viewmat
from tracegs.data.scene import load_scene
from tracegs.run import RunError, load_run, save_tensors
from tracegs.segment.command import labels_file
from tracegs.segment.masks import colours
from tracegs.view.camera import camera_from_view, pose_from_viewmat, vertical_fov, viewmat_from_pose
from tracegs.view.scene import dataset_cameras, find_segments, phase, render_view
from tracegs.view.server import round_step

FIXTURE = Path(__file__).parents[1] / "fixtures" / "run_1668a0e"  # a tiny trained TRACE run


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("view")
    scene = write_tiny_scene(root / "scene")
    shutil.copytree(FIXTURE, root / "run")
    return root / "run", scene


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def project(camera, point) -> np.ndarray:
    """Pixel (u, v) of the world point ``point`` seen by ``camera``."""
    p = camera.viewmat.double() @ torch.tensor([*point, 1.0], dtype=torch.float64)
    uvw = camera.K.double() @ p[:3]
    return (uvw[:2] / uvw[2]).numpy()


def test_a_viser_camera_looking_down_projects_world_points_where_opencv_axes_put_them():
    # viser's camera at (0, 0, 5) turned 180 degrees about x: camera +z (forward) is world -z, camera
    # +y (down in the image) is world -y, camera +x (right) is world +x.
    wxyz = (0.0, 1.0, 0.0, 0.0)
    fov_y, width, aspect = math.radians(60.0), 200, 2.0
    camera = camera_from_view(wxyz, (0.0, 0.0, 5.0), fov_y, aspect, width)
    assert (camera.width, camera.height) == (200, 100)
    f = 50.0 / math.tan(math.radians(30.0))  # half the height over tan(fov_y / 2)
    np.testing.assert_allclose(project(camera, (0.0, 0.0, 0.0)), [100.0, 50.0], atol=1e-4)
    np.testing.assert_allclose(project(camera, (0.5, 0.0, 0.0)), [100.0 + f * 0.1, 50.0], atol=1e-4)
    np.testing.assert_allclose(project(camera, (0.0, 0.5, 0.0)), [100.0, 50.0 - f * 0.1], atol=1e-4)
    torch.testing.assert_close(camera.center.double(), torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64))
    assert vertical_fov(camera) == pytest.approx(fov_y)


def test_a_pose_and_its_viewmat_round_trip_and_agree_with_viser_transforms():
    from viser import transforms as tf

    viewmat = look_at_viewmat((2.0, -3.0, 1.5), (0.1, 0.2, 0.0), (0.0, 0.0, 1.0))
    wxyz, position = pose_from_viewmat(viewmat)
    # viser's convention: P_world = R(wxyz) p_camera + position
    R = tf.SO3(wxyz).as_matrix()
    np.testing.assert_allclose(R, viewmat[:3, :3].double().numpy().T, atol=1e-6)
    np.testing.assert_allclose(position, [2.0, -3.0, 1.5], atol=1e-5)
    torch.testing.assert_close(viewmat_from_pose(wxyz, position), viewmat, atol=1e-5, rtol=0)


def test_the_viewer_frame_from_a_dataset_cameras_pose_is_that_cameras_render(tiny_run):
    run, scene = tiny_run
    loaded = load_run(run, device="cpu")
    cam = load_scene(scene, "test").frames[0].camera
    wxyz, position = pose_from_viewmat(cam.viewmat)
    view = camera_from_view(wxyz, position, vertical_fov(cam), cam.width / cam.height, cam.width)
    predictor = loaded.predictor.with_background(torch.ones(3))
    gaussians = predictor.gaussians_at(1.2)
    expected = predictor.render(cam, gaussians=gaussians).numpy()
    got = render_view(predictor, gaussians, view)
    assert got.shape == expected.shape and got.dtype == np.uint8
    assert np.abs(got / 255.0 - expected).max() <= 1 / 255 + 1e-4
    assert expected.std() > 0.01  # the run is seen: not a blank image


def test_the_f_defo_motion_is_the_deformation_field_at_every_time(tiny_run):
    predictor = load_run(tiny_run[0], device="cpu").predictor
    model = predictor.model
    for t in (0.0, 0.5, predictor.t_max, 1.0, 1.4):
        for name, value in predictor.gaussians_at(t, "f_defo").items():
            torch.testing.assert_close(value, model.deform(t)[name])
    t = 0.5 * predictor.handover_time()  # inside the span both are f_defo
    torch.testing.assert_close(predictor.gaussians_at(t, "trace"), predictor.gaussians_at(t, "f_defo"))
    with pytest.raises(ValueError, match="motion 'defgs'"):
        predictor.gaussians_at(1.0, "defgs")


def test_phase_says_observed_up_to_the_training_end_and_predicted_after():
    assert "observed" in phase(0.6, 0.6, "trace") and "predicted" not in phase(0.6, 0.6, "trace")
    assert "predicted" in phase(0.61, 0.6, "trace") and "physics" in phase(0.61, 0.6, "trace")
    assert "DefGS" in phase(0.9, 0.6, "f_defo")
    assert "MuJoCo" in phase(0.9, 0.6, "simulator")


def test_the_simulator_motion_is_offered_with_the_flag_and_moves_by_the_mujoco_model(tiny_run):
    pytest.importorskip("mujoco")
    from tracegs.view import serve

    run, scene = tiny_run
    viewer = serve(run, port=free_port(), data=scene, device="cpu", block=False, simulator=True)
    try:
        assert "MuJoCo model" in viewer.motion.options
        t = viewer.t_max + 0.1
        moved = viewer._gaussians(t, "simulator")["means"]
        simulated = viewer.simulated
        expected = viewer.predictor.gaussians_carried(t, simulated.labels, simulated.transforms)["means"]
        torch.testing.assert_close(moved, expected)
    finally:
        viewer.stop()
    plain = serve(run, port=free_port(), data=scene, device="cpu", block=False)
    try:
        assert "MuJoCo model" not in plain.motion.options
    finally:
        plain.stop()


def test_dataset_cameras_once_per_pose_and_a_note_without_a_scene(tiny_run, tmp_path):
    _, scene = tiny_run
    found = dataset_cameras(scene)
    # write_tiny_scene: cameras 0-2 train and the last one val up to t_train_end; all 4 test after it,
    # at the poses already shown
    assert {s: len(c) for s, c in found.cameras.items()} == {"train": 3, "val": 1, "test": 0}
    train = load_scene(scene, "train").frames
    torch.testing.assert_close(found.cameras["train"][1].viewmat, train[1 * 3].camera.viewmat)
    assert found.note == ""
    missing = dataset_cameras(tmp_path / "nowhere")
    assert missing.cameras == {} and str(tmp_path / "nowhere") in missing.note


def test_segments_are_offered_only_when_the_run_has_them_and_tint_the_image(tiny_run, tmp_path):
    run, scene = tiny_run
    segments, note = find_segments(run, 10)
    assert segments is None and "tracegs segment" in note
    loaded = load_run(run, device="cpu")
    n = loaded.model.gaussians["means"].shape[0]
    labelled = tmp_path / "run"
    shutil.copytree(run, labelled)
    labels = torch.arange(n) % 2
    save_tensors({"labels": labels, "k": 2, "has_static": False}, labels_file(labelled, "physics"))
    missing, note = find_segments(labelled, n + 1)
    assert missing is None and f"{n} labels for {n + 1} Gaussians" in note
    segments, note = find_segments(labelled, n)
    assert note == "" and segments.k == 2 and torch.equal(segments.labels, labels)
    np.testing.assert_allclose(segments.palette, colours(2, False))
    cam = load_scene(scene, "train").frames[0].camera
    predictor = loaded.predictor.with_background(torch.ones(3))
    gaussians = predictor.gaussians_at(0.3)
    plain = render_view(predictor, gaussians, cam).astype(float)
    painted = render_view(predictor, gaussians, cam, segments).astype(float)
    label_image, _ = predictor.render_labels(cam, labels, 2, gaussians=gaussians)
    inside = label_image > 0
    assert inside.any() and not inside.all()
    np.testing.assert_array_equal(painted[~inside], plain[~inside])  # the background is not tinted
    assert np.abs(painted[inside] - plain[inside]).mean() > 5.0


def test_slider_steps_read_well():
    assert [round_step(x) for x in (0.0038, 0.002, 0.0099, 0.3, 7.0, 1e-5)] == [
        0.002,
        0.002,
        0.005,
        0.2,
        5.0,
        1e-5,
    ]


def test_serve_answers_with_viser_page_and_stops(tiny_run, tmp_path, capsys):
    from tracegs.view import serve

    run, scene = tiny_run
    port = free_port()
    viewer = serve(run, port=port, data=scene, device="cpu", block=False)
    try:
        assert viewer.port == port and viewer.url == f"http://127.0.0.1:{port}/"
        assert viewer.url in capsys.readouterr().out
        assert len(viewer.frusta) == 4
        assert viewer.time.max == pytest.approx(2 * load_run(run, device="cpu").state.t_max)
        assert viewer.paint.disabled  # no segmentation in this run
        with urllib.request.urlopen(viewer.url, timeout=10) as page:
            html = page.read().decode()
        assert page.status == 200 and "<title>Viser</title>" in html
    finally:
        viewer.stop()
    with pytest.raises(OSError):
        urllib.request.urlopen(viewer.url, timeout=2)


def test_serve_without_the_scene_folder_still_serves_and_bad_flags_are_named(tiny_run, tmp_path):
    from tracegs.view import serve

    run, _ = tiny_run
    viewer = serve(run, port=free_port(), data=tmp_path / "gone", device="cpu", block=False, t_end=3.0)
    try:
        assert viewer.frusta == [] and viewer.time.max == 3.0
        with urllib.request.urlopen(viewer.url, timeout=10) as page:
            assert page.status == 200
    finally:
        viewer.stop()
    with pytest.raises(RunError, match="--port 70000"):
        serve(run, port=70000, block=False)
    with pytest.raises(RunError, match="--t-end -1"):
        serve(run, port=free_port(), t_end=-1, device="cpu", block=False)
