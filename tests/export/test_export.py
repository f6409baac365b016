"""``tracegs export``: the Gaussians at any time (the predicted future included) written as PLY and
``.splat``, read back to the same Gaussians and the same image; numbered sequences with their json;
labelled exports in the segment palette; clear errors for bad times and missing labels."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import torch
from tests.conftest import randomised_model, write_tiny_scene
from torch import nn

from tracegs.config import make_config
from tracegs.data.cameras import Camera, look_at_viewmat
from tracegs.export.command import export_run, parse_times
from tracegs.export.palette import colours
from tracegs.export.ply import read_gaussians, write_gaussians
from tracegs.export.splat import SPLAT_DTYPE, read_splat, write_splat
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.models.gaussians import SH_C0
from tracegs.run import RunError, load_run, save_tensors
from tracegs.train.trainer import Trainer


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("export")
    scene = write_tiny_scene(root / "scene")
    Trainer(make_config("tiny", data=scene, run=root / "run", device="cpu"), progress=False).train()
    return root / "run"


def with_gaussians(model, params: dict[str, torch.Tensor]):
    """A copy of ``model`` whose Gaussians are ``params`` (e.g. read back from a file)."""
    other = copy.deepcopy(model)
    other.gaussians = nn.ParameterDict({k: nn.Parameter(v.clone()) for k, v in params.items()})
    return other


def test_a_predicted_time_reloads_to_the_same_gaussians_and_the_same_image(tmp_path):
    model = randomised_model(make_config("tiny", device="cpu", bf16=False))
    t = 1.2  # past the training span: the learned physics
    background = torch.tensor([1.0, 1.0, 1.0])
    predictor = Predictor(model, ExtrapolationState(t_max=0.5), background=background)
    params = predictor.parameters_at(t)
    expected = predictor.gaussians_at(t)
    assert (expected["means"] - model.gaussians["means"]).abs().max() > 1e-3  # the fields do move them
    back = read_gaussians(write_gaussians(params, tmp_path / "g.ply"))
    for name in ("means", "quats", "scales"):
        assert torch.equal(back[name], expected[name]), name
    for name in ("opacities", "sh0", "shN"):
        assert torch.equal(back[name], model.gaussians[name].detach()), name
    camera = Camera(
        look_at_viewmat((2.5, 1.0, 1.5)), torch.tensor([[40.0, 0, 16], [0, 40, 16], [0, 0, 1]]), 32, 32
    )
    original = predictor.render(camera, t)
    reloaded = Predictor(with_gaussians(model, back), predictor.state, background=background)
    rendered = reloaded.render(camera, gaussians=back)
    assert original.std() > 0.01 and torch.equal(rendered, original)


def test_times_parse_inclusive_of_the_stop_on_the_grid():
    assert parse_times("0:1.5:0.25") == [0.25 * i for i in range(7)]
    assert parse_times("0:1:0.3") == pytest.approx([0.0, 0.3, 0.6, 0.9])  # 1 is off the grid
    assert parse_times("0.1:0.3:0.1") == pytest.approx([0.1, 0.2, 0.3])  # (0.3 - 0.1) / 0.1 < 2 in floats
    assert parse_times("0.7:0.7:0.1") == [0.7]
    assert len(parse_times("0:0.9999:0.0001")) == 10_000  # at the limit


@pytest.mark.parametrize(
    "spec, message",
    [
        ("0:1:0", "step must be"),
        ("0:1:-0.1", "step must be"),
        ("0:1:nan", "step must be"),
        ("1:0:0.1", "before the start"),
        ("nan:1:0.1", "finite"),
        ("0:inf:0.1", "finite"),
        ("-1:1:0.5", ">= 0"),
        ("0:1", "START:STOP:STEP"),
        ("a:b:c", "START:STOP:STEP"),
        ("0:1:0.00001", "more than the 10000"),
    ],
)
def test_bad_time_specs_are_refused_naming_the_flag(spec, message):
    with pytest.raises(ValueError, match=message) as err:
        parse_times(spec)
    assert "--times" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -0.5])
def test_bad_single_times_are_refused_before_the_run_is_read(tmp_path, bad):
    with pytest.raises(ValueError, match="--time must be a finite time >= 0") as err:
        export_run(tmp_path / "nowhere", time=bad)
    assert "\n" not in str(err.value)


def test_times_far_past_the_training_span_are_refused(run, tmp_path):
    with pytest.raises(ValueError, match="--time 1e[+]09 is beyond the limit"):
        export_run(run, time=1e9, device="cpu", ply=tmp_path / "far.ply")
    with pytest.raises(ValueError, match="--times stop 100 is beyond the limit"):
        export_run(run, times="0:100:10", device="cpu", out=tmp_path / "far")
    assert not (tmp_path / "far.ply").exists() and not (tmp_path / "far").exists()


def test_splat_is_32_bytes_a_gaussian_and_reads_back_within_quantisation(tmp_path):
    g = torch.Generator().manual_seed(1)
    n = 50
    params = {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 3,
        "opacities": 3 * torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, 3, 3, generator=g),
    }
    path = write_splat(params, tmp_path / "g.splat")
    assert SPLAT_DTYPE.itemsize == 32 and path.stat().st_size == 32 * n
    back = read_splat(path)
    # the file's order: match each record to its Gaussian by position (stored exactly)
    order = [int(np.flatnonzero((params["means"].numpy() == m).all(1))[0]) for m in back["means"]]
    assert sorted(order) == list(range(n))
    p = {k: v.double().numpy()[order] for k, v in params.items()}
    alpha = 1 / (1 + np.exp(-p["opacities"]))
    importance = np.exp(p["scales"]).prod(1) * alpha
    assert np.all(np.diff(importance) <= 0)  # largest first
    np.testing.assert_allclose(back["scales"], np.exp(p["scales"]), rtol=1e-6)
    rgba = np.concatenate([np.clip(0.5 + SH_C0 * p["sh0"][:, 0], 0, 1), alpha[:, None]], 1)
    assert np.abs(back["rgba"] - rgba).max() <= 0.5 / 255 + 1e-9
    unit = p["quats"] / np.linalg.norm(p["quats"], axis=1, keepdims=True)
    assert np.abs(back["quats"] - np.clip(unit, -1, 127 / 128)).max() <= 0.5 / 128 + 1e-9
    (tmp_path / "short.splat").write_bytes(path.read_bytes()[:-1])
    with pytest.raises(ValueError, match="short.splat: not a .splat"):
        read_splat(tmp_path / "short.splat")


def test_one_time_in_both_formats_is_the_run_at_that_time(run, tmp_path):
    loaded = load_run(run, "cpu")
    t = 1.25
    report = export_run(run, time=t, ply=tmp_path / "out.ply", fmt="both", device="cpu")
    assert report["files"] == [str(tmp_path / "out.ply"), str(tmp_path / "out.splat")]
    assert report["predicted"] == [t > loaded.state.t_max] == [True]
    back = read_gaussians(tmp_path / "out.ply")
    assert report["gaussians"] == len(back["means"]) == len(loaded.model.gaussians["means"])
    expected = loaded.predictor.gaussians_at(t)
    assert torch.equal(back["means"], expected["means"]) and torch.equal(back["quats"], expected["quats"])
    assert (tmp_path / "out.splat").stat().st_size == 32 * report["gaussians"]
    default = export_run(run, time=0.5, device="cpu", fmt="splat")
    assert default["files"] == [str(run / "export" / "gaussians_t0.500.splat")] and default["predicted"] == [
        False
    ]


def test_a_sequence_is_numbered_with_its_times_and_predicted_frames(run, tmp_path):
    loaded = load_run(run, "cpu")
    report = export_run(
        run, times="0:1.5:0.5", out=tmp_path / "seq", ply="fan.ply", device="cpu", progress=False
    )
    names = [f"fan_{i:04d}.ply" for i in range(4)]
    assert report["files"] == [str(tmp_path / "seq" / n) for n in names]
    index = json.loads((tmp_path / "seq" / "fan.json").read_text())
    assert report["index"] == str(tmp_path / "seq" / "fan.json")
    t_max = loaded.state.t_max
    assert index["times"] == [0.0, 0.5, 1.0, 1.5] and index["files"] == {"ply": names}
    assert index["t_max"] == pytest.approx(t_max) and 0.5 < t_max < 1.0
    assert index["predicted"] == report["predicted"] == [False, False, True, True]
    for name, t in zip(names, index["times"], strict=True):
        expected = loaded.predictor.gaussians_at(t)["means"]
        assert torch.equal(read_gaussians(tmp_path / "seq" / name)["means"], expected)
    default = export_run(run, times="0:0.2:0.1", fmt="both", device="cpu", progress=False)
    folder = run / "export" / "sequence"
    assert sorted(p.name for p in folder.iterdir()) == sorted(
        ["frame.json"] + [f"frame_{i:04d}{s}" for i in range(3) for s in (".ply", ".splat")]
    )
    assert len(default["files"]) == 6


def test_labelled_export_colours_are_the_palette(run, tmp_path):
    with pytest.raises(RunError, match="tracegs segment --run") as err:
        export_run(run, time=0.3, labels=True, device="cpu", ply=tmp_path / "x.ply")
    assert "segments.pt" in str(err.value) and not (tmp_path / "x.ply").exists()
    n = len(load_run(run, "cpu").model.gaussians["means"])
    labels = torch.arange(n) % 3
    save_tensors({"labels": labels, "k": 3, "has_static": True}, run / "segments.pt")
    try:
        export_run(run, time=1.1, labels=True, fmt="both", ply=tmp_path / "seg.ply", device="cpu")
        palette = colours(3, has_static=True)  # grey for the static group, then red, blue
        back = read_gaussians(tmp_path / "seg.ply")
        rgb = (0.5 + SH_C0 * back["sh0"][:, 0]).double().numpy()
        np.testing.assert_allclose(rgb, palette[labels.numpy()], atol=1e-6)
        assert back["shN"].shape[1] > 0 and torch.all(back["shN"] == 0)
        splat = read_splat(tmp_path / "seg.splat")
        assert {tuple(c) for c in np.rint(255 * splat["rgba"][:, :3]).astype(int)} == {
            tuple(c) for c in np.rint(255 * palette).astype(int)
        }
        save_tensors({"labels": labels[:-1], "k": 3, "has_static": True}, run / "segments.pt")
        with pytest.raises(RunError, match=f"{n - 1} labels for the run's {n} Gaussians"):
            export_run(run, time=0.3, labels=True, device="cpu", ply=tmp_path / "y.ply")
    finally:
        (run / "segments.pt").unlink()


def test_bad_arguments_are_refused_before_anything_is_read(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(ValueError, match="--format 'gif'"):
        export_run(missing, time=1.0, fmt="gif")
    with pytest.raises(ValueError, match="not both"):
        export_run(missing, time=1.0, times="0:1:0.5")
    with pytest.raises(ValueError, match="give --time T or --times"):
        export_run(missing)
    with pytest.raises(FileNotFoundError, match="config.json"):
        export_run(missing, time=1.0)


def test_a_trained_run_exports_to_mjcf_and_urdf_that_mujoco_and_yourdfpy_load(run, tmp_path):
    mujoco = pytest.importorskip("mujoco")
    from tracegs.export.simulate import load_urdf
    from tracegs.export.simulator import export_simulator

    report = export_simulator(run, mjcf=tmp_path / "scene.xml", urdf=tmp_path / "urdf", device="cpu")
    model = mujoco.MjModel.from_xml_path(str(tmp_path / "scene.xml"))
    assert model.nkey == 1 and report["check"]["finite"]
    assert len(report["bodies"]) == model.nbody - 1  # the world and one body per part
    robot = load_urdf(tmp_path / "urdf" / f"{run.name}.urdf")
    assert set(robot.link_map) == {"world"} | {b["body"] for b in report["bodies"]}
    for entry in report["check"]["against_the_run"]:
        assert entry["mean_path_error"] is None or entry["mean_path_error"] >= 0
    with pytest.raises(ValueError, match="--mjcf"):
        export_simulator(run)
