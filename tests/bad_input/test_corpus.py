"""The bad-input corpus: malformed scenes, flags, run folders and images, each run through the public
command line (``tracegs.cli.main``) as a user would type it.

Every case must end with a non-zero exit status and exactly one line on stderr,
``tracegs COMMAND: error: ...``, that names the file (or flag) and the cause, no traceback, and leave
what was there before (the scene, the run folder) byte for byte as it was. The positive controls
(grey, 16-bit, RGB images) must train, so that the corpus can tell a refusal from a crash.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from tests.bad_input.images import write_png16
from tests.conftest import write_tiny_scene
from tests.test_run import _Payload
from tracegs.cli import main

SIZE = 16
"""Image side of the corpus scene (SSIM, which eval computes, needs at least 11)."""


# ----- running the command line ---------------------------------------------------------------------
def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """``(exit status, stdout, stderr)`` of ``tracegs ARGV`` run in this process."""
    capsys.readouterr()
    try:
        main([str(a) for a in argv])
        code = 0
    except SystemExit as exit_:
        code = exit_.code if isinstance(exit_.code, int) else 1
    out, err = capsys.readouterr()
    return code, out, err


def assert_clean_error(argv, capsys, where: str, keyword: str, after_progress: bool = False) -> str:
    """Run ``argv``; it must fail with one stderr line naming ``where`` and saying ``keyword`` (with
    ``after_progress``: after the progress bar of the steps that ran, and nothing else)."""
    code, _, err = run_cli(argv, capsys)
    lines = err.strip().split("\n")
    if after_progress:
        assert all("%|" in line for line in lines[:-1]), err
        lines = lines[-1:]
    assert code == 1, f"exit status {code}, stderr: {err}"
    assert "Traceback" not in err
    assert len(lines) == 1, err
    assert lines[0].startswith(f"tracegs {argv[0]}: error: "), lines[0]
    assert where in lines[0] and keyword in lines[0], lines[0]
    assert "this is a bug" not in lines[0]
    return lines[0]


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


# ----- the inputs -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pristine(tmp_path_factory) -> Path:
    return write_tiny_scene(tmp_path_factory.mktemp("corpus") / "scene", size=SIZE)


@pytest.fixture
def scene(pristine, tmp_path) -> Path:
    """A copy of the corpus scene for a case to break."""
    return Path(shutil.copytree(pristine, tmp_path / "scene"))


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> tuple[Path, Path]:
    """A tiny run trained once through the command line: ``(scene, run)``."""
    root = tmp_path_factory.mktemp("trained")
    scene = write_tiny_scene(root / "scene", size=SIZE)
    main(["train", "--data", str(scene), "--run", str(root / "run"), "--preset", "tiny", "--device", "cpu"])
    assert (root / "run" / "extrapolation.pt").is_file()
    return scene, root / "run"


@pytest.fixture
def run(trained, tmp_path) -> Path:
    """A copy of the trained run (it reads the trained scene), with an earlier eval.json in it."""
    copy = Path(shutil.copytree(trained[1], tmp_path / "run"))
    (copy / "eval.json").write_text('{"earlier": "result"}')
    return copy


def edit_json(scene: Path, split: str, edit) -> None:
    """Rewrite ``transforms_SPLIT.json`` with ``edit(meta)`` applied (NaN and Inf as Python writes them)."""
    path = scene / f"transforms_{split}.json"
    meta = json.loads(path.read_text())
    edit(meta)
    path.write_text(json.dumps(meta))


def frame(k: int, **changes):
    """An edit that sets keys of training frame ``k`` (a value of ``None`` deletes the key)."""

    def edit(meta):
        for key, value in changes.items():
            if value is None:
                meta["frames"][k].pop(key, None)
            else:
                meta["frames"][k][key] = value

    return edit


def top(**changes):
    """An edit that sets top-level keys of the file (``None`` deletes the key)."""

    def edit(meta):
        for key, value in changes.items():
            if value is None:
                meta.pop(key, None)
            else:
                meta[key] = value

    return edit


def image(scene: Path, k: int = 0) -> Path:
    return scene / json.loads((scene / "transforms_train.json").read_text())["frames"][k]["file_path"]


def _truncate(path: Path) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _every_frame_after(t: float):
    def edit(meta):
        for f in meta["frames"]:
            f["time"] = max(f["time"], t)

    return edit


def _json_as_folder(scene: Path) -> None:
    (scene / "transforms_train.json").unlink()
    (scene / "transforms_train.json").mkdir()


def _wider(path: Path) -> None:
    iio.imwrite(path, np.zeros((SIZE, SIZE + 4, 3), np.uint8))


def _remove_frames(meta):
    del meta["frames"]


def _mutate_json(split, edit):
    return lambda scene: edit_json(scene, split, edit)


def _write(name: str, content: bytes):
    return lambda scene: (scene / name).write_bytes(content)


def _replace_image(k: int, fn):
    return lambda scene: fn(image(scene, k))


POSE_NAN = [[math.nan, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
POSE_INF = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, math.inf], [0, 0, 0, 1]]
TRAIN_JSON = "transforms_train.json"

JSON_CASES = [
    # (name, edit of transforms_train.json, the cause its message names)
    ("no frames", _remove_frames, "no 'frames'"),
    ("frames not a list", top(frames={"a": 1}), "must be a list"),
    ("empty split", top(frames=[]), "'frames' is empty"),
    ("frame not an object", top(frames=[3]), "frame 0 is not an object"),
    ("no file_path", frame(1, file_path=None), "'file_path'"),
    ("file_path not a string", frame(1, file_path=7), "non-empty string"),
    ("file_path escapes", frame(1, file_path="../other/x.png"), "leaves the scene folder"),
    ("file_path absolute", frame(1, file_path="/etc/hosts.png"), "is absolute"),
    ("no transform_matrix", frame(0, transform_matrix=None), "transform_matrix"),
    ("3x4 matrix", frame(0, transform_matrix=[[1, 0, 0, 0]] * 3), "finite 4x4"),
    ("NaN in pose", frame(0, transform_matrix=POSE_NAN), "finite 4x4"),
    ("Inf in pose", frame(2, transform_matrix=POSE_INF), "finite 4x4"),
    ("pose of strings", frame(0, transform_matrix="eye"), "4x4"),
    ("one frame without time", frame(2, time=None), "frame 2: no 'time'"),
    ("time a string", frame(1, time="soon"), "'time' must be a number"),
    ("time NaN", frame(1, time=math.nan), "finite number"),
    ("time out of range", frame(1, time=2.0), "outside [0, 1]"),
    ("time negative", frame(1, time=-0.5), "outside [0, 1]"),
    ("no camera_angle_x", top(camera_angle_x=None), "no intrinsics"),
    ("negative camera_angle_x", top(camera_angle_x=-0.7), "positive"),
    ("zero camera_angle_x", top(camera_angle_x=0), "positive"),
    ("camera_angle_x of 4 rad", top(camera_angle_x=4.0), "below pi"),
    ("camera_angle_x a string", top(camera_angle_x="wide"), "must be a number"),
    ("negative fl_x", frame(1, fl_x=-20.0), "positive"),
    ("Inf fl_x", frame(1, fl_x=math.inf), "positive"),
    ("w not whole", top(w=15.5, h=16), "whole numbers"),
    ("t_train_end a string", top(t_train_end="late"), "'t_train_end'"),
    ("aabb malformed", top(aabb=[1, 2, 3]), "'aabb'"),
    ("background malformed", top(background="white"), "'background'"),
]

FILE_CASES = [
    # (name, mutation of the scene, the file the message names, the cause)
    ("json syntax error", _write(TRAIN_JSON, b'{"frames": [}'), TRAIN_JSON, "not valid JSON"),
    ("json not utf-8", _write(TRAIN_JSON, b"\xff\xfe\x00"), TRAIN_JSON, "not valid JSON"),
    ("json is a list", _write(TRAIN_JSON, b"[1, 2]"), TRAIN_JSON, "got a list"),
    ("no transforms_train.json", lambda s: (s / TRAIN_JSON).unlink(), TRAIN_JSON, "file not found"),
    ("transforms_train.json a folder", _json_as_folder, TRAIN_JSON, "is a folder"),
    ("missing image", _replace_image(0, lambda p: p.unlink()), "c0_f0.png", "not found"),
    ("missing later image", _replace_image(2, lambda p: p.unlink()), "c0_f2.png", "not found"),
    ("zero-byte first image", _replace_image(0, lambda p: p.write_bytes(b"")), "c0_f0.png", "empty file"),
    ("zero-byte later image", _replace_image(3, lambda p: p.write_bytes(b"")), "c1_f0.png", "empty file"),
    ("truncated image", _replace_image(1, _truncate), "c0_f1.png", "truncated"),
    ("text as image", _replace_image(1, lambda p: p.write_text("hello")), "c0_f1.png", "not an image"),
    ("image of another size", _replace_image(2, _wider), "c0_f2.png", "expected 16x16"),
    (
        "every frame past t_train_end",
        _mutate_json("train", _every_frame_after(0.9)),
        "scene",
        "no training frames",
    ),
]
SCENE_CASES = [(n, _mutate_json("train", e), TRAIN_JSON, k) for n, e, k in JSON_CASES] + FILE_CASES


@pytest.mark.parametrize("name, mutate, where, keyword", SCENE_CASES, ids=[c[0] for c in SCENE_CASES])
def test_a_malformed_scene_is_one_line_naming_the_file(scene, tmp_path, capsys, name, mutate, where, keyword):
    mutate(scene)
    before = snapshot(scene)
    argv = ["train", "--data", scene, "--run", tmp_path / "run", "--preset", "tiny", "--device", "cpu"]
    assert_clean_error(argv, capsys, where, keyword)
    assert snapshot(scene) == before
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


FLAG_CASES = [
    # (flags added to a good `tracegs train`, the flag the message names, the cause)
    (["--downscale", "0"], "--downscale", "positive integer, got 0"),
    (["--downscale", "-2"], "--downscale", "positive integer"),
    (["--downscale", "3"], "--downscale 3", "does not divide"),
    (["--checkpoint-every", "0"], "--checkpoint-every", "positive integer"),
    (["--log-every", "0"], "--log-every", "positive integer"),
    (["--t-train-end", "0"], "--t-train-end", "(0, 1]"),
    (["--t-train-end", "-0.5"], "--t-train-end", "(0, 1]"),
    (["--t-train-end", "1.5"], "--t-train-end", "(0, 1]"),
    (["--t-train-end", "nan"], "--t-train-end", "got nan"),
    (["--init-points", "0"], "--init-points", "positive integer"),
    (["--static-iterations", "-1"], "--static-iterations", "non-negative"),
    (["--static-iterations", "0", "--dynamic-iterations", "0"], "--dynamic-iterations", "at least 1"),
    (["--densify.max-gaussians", "0"], "--densify.max-gaussians", "positive integer"),
    (["--optim.means-lr", "nan"], "--optim.means-lr", "finite"),
    (["--stage2.dt-frames", "0"], "--stage2.dt-frames", "positive"),
    (["--device", "tpu"], "--device", "expected auto, cpu"),
]


@pytest.mark.parametrize("flags, where, keyword", FLAG_CASES, ids=[" ".join(c[0]) for c in FLAG_CASES])
def test_a_bad_training_setting_is_one_line_naming_the_flag(
    pristine, tmp_path, capsys, flags, where, keyword
):
    argv = ["train", "--data", pristine, "--run", tmp_path / "run", "--preset", "tiny", "--device", "cpu"]
    assert_clean_error(argv + flags, capsys, where, keyword)
    assert not (tmp_path / "run" / "checkpoint.pt").exists()


def test_a_training_that_prunes_every_gaussian_stops_with_one_line(pristine, tmp_path, capsys):
    argv = ["train", "--data", pristine, "--run", tmp_path / "run", "--preset", "tiny", "--device", "cpu"]
    flags = ["--densify.prune-opacity", "0.99"]  # every Gaussian starts less opaque than that
    assert_clean_error(argv + flags, capsys, "--densify.prune-opacity", "prune every Gaussian", True)


def _plant_pickle(run: Path) -> None:
    """A checkpoint whose unpickling would create ``run/../executed``: what a malicious one would do."""
    ckpt = torch.load(run / "checkpoint.pt", weights_only=True)
    ckpt["extra"] = _Payload(run.parent / "executed")
    torch.save(ckpt, run / "checkpoint.pt")


def _edit_checkpoint(edit):
    def mutate(run: Path) -> None:
        ckpt = torch.load(run / "checkpoint.pt", weights_only=True)
        edit(ckpt)
        torch.save(ckpt, run / "checkpoint.pt")

    return mutate


def _as_file(run: Path) -> None:
    shutil.rmtree(run)
    run.write_text("not a folder")


def _config(edit):
    def mutate(run: Path) -> None:
        path = run / "config.json"
        data = json.loads(path.read_text())
        edit(data)
        path.write_text(json.dumps(data))

    return mutate


def _nothing(run: Path) -> None:
    pass


RUN_CASES = [
    # (name, mutation of the run folder, the command after `--run RUN`, where, cause)
    ("render --time nan", _nothing, ["render", "--time", "nan"], "--time", "finite"),
    ("render --time inf", _nothing, ["render", "--time", "inf"], "--time", "finite"),
    ("render --time -1", _nothing, ["render", "--time", "-1"], "--time", ">= 0"),
    ("render --time 1e9", _nothing, ["render", "--time", "1e9"], "--time", "beyond the limit"),
    ("render --t-end nan", _nothing, ["render", "--video", "--t-end", "nan"], "--t-end", "finite"),
    ("render --frames 0", _nothing, ["render", "--video", "--frames", "0"], "--frames", "positive integer"),
    (
        "unknown camera index",
        _nothing,
        ["render", "--camera", "test:99"],
        "--camera",
        "choose an index in 0-",
    ),
    ("unknown camera split", _nothing, ["render", "--camera", "side:0"], "--camera", "train, val, test"),
    ("malformed orbit", _nothing, ["render", "--camera", "orbit:left"], "--camera", "azimuth"),
    ("image --out of a video type", _nothing, ["render", "--out", "x.mp4"], "--out", ".png"),
    ("render on a missing device", _nothing, ["render", "--device", "cuda:7"], "--device", "cuda:7"),
    ("run folder is a file", _as_file, ["render"], "config.json", "no config.json"),
    (
        "run without config.json",
        lambda r: (r / "config.json").unlink(),
        ["eval"],
        "config.json",
        "no config.json",
    ),
    (
        "config.json syntax error",
        lambda r: (r / "config.json").write_text("{"),
        ["render"],
        "config.json",
        "not valid JSON",
    ),
    (
        "config.json of another tool",
        _config(lambda d: d.update(learning_rate=1)),
        ["render"],
        "config.json",
        "unknown config field",
    ),
    (
        "config.json with an unknown choice",
        _config(lambda d: d["extrapolation"].update(surface_painters="sideways")),
        ["render"],
        "config.json",
        "must be one of edge, hold",
    ),
    (
        "run without checkpoint",
        lambda r: (r / "checkpoint.pt").unlink(),
        ["render"],
        "checkpoint.pt",
        "no checkpoint",
    ),
    (
        "truncated checkpoint",
        lambda r: _truncate(r / "checkpoint.pt"),
        ["eval"],
        "checkpoint.pt",
        "not a readable checkpoint",
    ),
    ("planted pickle payload", _plant_pickle, ["render"], "checkpoint.pt", "refused"),
    (
        "checkpoint of other bytes",
        lambda r: (r / "checkpoint.pt").write_bytes(b"not a checkpoint"),
        ["render"],
        "checkpoint.pt",
        "not a readable checkpoint",
    ),
    (
        "eval on a moved scene",
        _config(lambda d: d.update(data="/nonexistent/scene")),
        ["eval"],
        "/nonexistent/scene",
        "no scene here",
    ),
    (
        "eval --data of no scene",
        _nothing,
        ["eval", "--data", "/nonexistent/x"],
        "/nonexistent/x",
        "no scene here",
    ),
    (
        "calibrate --handover-frames -1",
        _nothing,
        ["calibrate", "--handover-frames", "-1"],
        "--handover-frames",
        "non-negative",
    ),
]
RUN_CASES += [
    (
        "empty checkpoint",
        lambda r: (r / "checkpoint.pt").write_bytes(b""),
        ["render"],
        "checkpoint.pt",
        "checkpoint",
    ),
    (
        "checkpoint of another version",
        _edit_checkpoint(lambda c: c.pop("model")),
        ["render"],
        "checkpoint.pt",
        "version",
    ),
]


def _run_case(run: Path, capsys, mutate, command, where, keyword, tmp_path) -> None:
    mutate(run)
    before = snapshot(run) if run.is_dir() else run.read_bytes()
    argv = [command[0], "--run", run, *command[1:]]
    assert_clean_error(argv, capsys, where, keyword)
    assert (snapshot(run) if run.is_dir() else run.read_bytes()) == before
    assert not (tmp_path / "executed").exists()  # the planted payload never ran


@pytest.mark.parametrize("name, mutate, command, where, keyword", RUN_CASES, ids=[c[0] for c in RUN_CASES])
def test_a_bad_run_folder_or_request_is_one_line_and_changes_nothing(
    run, tmp_path, capsys, name, mutate, command, where, keyword
):
    _run_case(run, capsys, mutate, command, where, keyword, tmp_path)


def test_eval_stopped_by_a_missing_test_image_keeps_the_earlier_result(trained, tmp_path, capsys):
    scene = Path(shutil.copytree(trained[0], tmp_path / "scene"))
    run = Path(shutil.copytree(trained[1], tmp_path / "run"))
    (run / "eval.json").write_text('{"earlier": "result"}')
    (scene / "test" / "c2_f3.png").unlink()
    assert_clean_error(
        ["eval", "--run", run, "--data", scene, "--no-lpips"], capsys, "c2_f3.png", "not found"
    )
    assert (run / "eval.json").read_text() == '{"earlier": "result"}'


METRICS_CASES = [
    ("different sizes", (SIZE + 2, SIZE), "differ in size"),
    ("zero-byte image", b"", "empty file"),
    ("truncated image", "truncate", "truncated"),
    ("missing image", None, "not found"),
]


@pytest.mark.parametrize("name, second, keyword", METRICS_CASES, ids=[c[0] for c in METRICS_CASES])
def test_metrics_on_a_bad_pair_names_the_file(tmp_path, capsys, name, second, keyword):
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    iio.imwrite(a, np.zeros((SIZE, SIZE, 3), np.uint8))
    if isinstance(second, tuple):
        iio.imwrite(b, np.zeros((*second, 3), np.uint8))
    elif second == "truncate":
        iio.imwrite(b, np.random.default_rng(0).integers(0, 255, (SIZE, SIZE, 3), dtype=np.uint8))
        _truncate(b)
    elif second is not None:
        b.write_bytes(second)
    line = assert_clean_error(["metrics", a, b, "--no-lpips"], capsys, "b.png", keyword)
    if isinstance(second, tuple):
        assert "a.png" in line  # both files of the pair


def test_resume_takes_no_other_training_flag(run, capsys):
    before = snapshot(run)
    assert_clean_error(["train", "--resume", run, "--seed", "3"], capsys, "--resume", "--seed")
    assert snapshot(run) == before


# ----- positive controls ----------------------------------------------------------------------------
def _grey(path: Path) -> None:
    iio.imwrite(path, iio.imread(path)[..., :3].mean(-1).astype(np.uint8))


def _grey16(path: Path) -> None:
    iio.imwrite(path, (iio.imread(path)[..., :3].mean(-1) * 257).astype(np.uint16))


def _rgba16(path: Path) -> None:
    write_png16(path, iio.imread(path).astype(np.uint16) * 257)


def _rgb(path: Path) -> None:
    iio.imwrite(path, iio.imread(path)[..., :3])


def _grey_alpha(path: Path) -> None:
    from PIL import Image

    Image.fromarray(iio.imread(path)).convert("LA").save(path)


CONTROLS = {
    "grey": _grey,
    "grey 16-bit": _grey16,
    "RGBA 16-bit": _rgba16,
    "RGB": _rgb,
    "grey + alpha": _grey_alpha,
}


@pytest.mark.parametrize("convert", CONTROLS.values(), ids=list(CONTROLS))
def test_images_of_every_common_layout_train(scene, tmp_path, capsys, convert):
    for path in sorted((scene / "train").glob("*.png")):
        convert(path)
    argv = ["train", "--data", scene, "--run", tmp_path / "run", "--preset", "tiny", "--device", "cpu"]
    argv += ["--static-iterations", "1", "--dynamic-iterations", "1"]
    code, out, err = run_cli(argv, capsys)
    assert code == 0, err
    assert json.loads(out[out.index("{") :])["iterations"] == 2


def test_a_split_without_any_time_is_a_static_scene(scene):
    from tracegs.data.scene import load_scene

    edit_json(scene, "train", lambda meta: [f.pop("time") for f in meta["frames"]])
    assert {f.time for f in load_scene(scene, "train").frames} == {0.0}


# ----- the command line itself ----------------------------------------------------------------------
def test_debug_shows_the_traceback(tmp_path):
    import subprocess
    import sys

    argv = [sys.executable, "-m", "tracegs", "render", "--run", str(tmp_path / "none"), "--debug"]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1
    assert "Traceback" in done.stderr and "FileNotFoundError" in done.stderr


def test_a_bug_prints_its_traceback_and_says_so(monkeypatch, capsys):
    import tracegs.cli as cli

    def broken(command, argv):
        raise TypeError("an unexpected type")

    monkeypatch.setattr(cli, "run_command", broken)
    code, _, err = run_cli(["render", "--run", "x"], capsys)
    assert code == 1 and "Traceback" in err
    assert err.strip().split("\n")[-1].startswith("tracegs render: error: this is a bug")
    assert "TypeError: an unexpected type" in err.strip().split("\n")[-1]


def test_ctrl_c_exits_130_with_one_line(monkeypatch, capsys):
    import tracegs.cli as cli

    def interrupted(command, argv):
        raise KeyboardInterrupt

    monkeypatch.setattr(cli, "run_command", interrupted)
    code, _, err = run_cli(["eval", "--run", "x"], capsys)
    assert code == 130 and err.strip() == "tracegs eval: interrupted"


def test_an_unknown_command_is_a_usage_error(capsys):
    code, _, err = run_cli(["trian"], capsys)
    assert code == 2 and err.strip().split("\n") == [err.strip()] and "'trian'" in err and "train" in err


def test_help_describes_every_command(capsys):
    import tracegs.cli as cli

    code, out, _ = run_cli(["--help"], capsys)
    assert code == 0
    for name, (cls, _) in cli.COMMANDS.items():
        line = next(li for li in out.splitlines() if li.strip().startswith(name + " "))
        assert cls.__doc__.strip().split("\n")[0] in line  # its docstring's first line
        assert len(line.split(None, 1)[1]) > 20  # a description, not only the name
