"""The fields' frame: a capture in other units or far from the origin is moved and scaled for the
fields (``TraceModel.set_field_frame``, ``train.trainer.field_frame``), and moves exactly as the same
scene at the origin would."""

import copy
import json
import math

import pytest
import torch
from tests.conftest import randomised_model, write_tiny_scene

from tracegs.config import apply_overrides, make_config
from tracegs.data.dataset import ViewDataset
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.models.trace import TraceModel
from tracegs.run import load_run
from tracegs.train.scene_frame import field_frame
from tracegs.train.trainer import Trainer

CENTER, SCALE = torch.tensor([50.0, -20.0, 3.0]), 8.0
VARIANTS = {
    "trace": {},
    "trace_4dgs": {"deformation.kind": "hexplane"},
    "order 3": {"dynamics.order": 3},
    "no equivalence": {"dynamics.equivalent": False},
    "defgs": {"method": "defgs"},
}


def _moved_copy(model: TraceModel) -> TraceModel:
    """The same model for the scene moved to ``CENTER`` and scaled by ``SCALE``."""
    moved = copy.deepcopy(model)
    with torch.no_grad():
        moved.gaussians["means"].copy_(CENTER + SCALE * model.gaussians["means"])
        moved.gaussians["scales"].add_(math.log(SCALE))
    moved.set_field_frame(CENTER, SCALE)
    return moved


@pytest.mark.parametrize("switch", VARIANTS.values(), ids=VARIANTS.keys())
def test_a_moved_and_scaled_scene_moves_the_same(switch):
    cfg = apply_overrides(make_config("tiny", device="cpu", bf16=False), switch)
    model = randomised_model(cfg)
    moved = _moved_copy(model)
    for m in (model, moved):
        m.begin_dynamic_stage()  # the HexPlane boxes the canonical Gaussians (in the fields' frame)
    predictor, other = (Predictor(m, ExtrapolationState(t_max=0.75)) for m in (model, moved))
    with torch.no_grad():
        pairs = {
            "f_defo": (predictor.gaussians_at(0.3), other.gaussians_at(0.3)),
            "extrapolated": (predictor.gaussians_at(1.4), other.gaussians_at(1.4)),
            "training": (model.training_state(0.4, 0.45)[0], moved.training_state(0.4, 0.45)[0]),
        }
    for name, (a, b) in pairs.items():
        assert (a["means"] - model.gaussians["means"]).abs().max() > 1e-3, name  # the fields do move them
        torch.testing.assert_close((b["means"] - CENTER) / SCALE, a["means"], atol=2e-5, rtol=0, msg=name)
        torch.testing.assert_close(b["quats"], a["quats"], atol=1e-5, rtol=0, msg=name)
        torch.testing.assert_close(b["scales"], a["scales"] + math.log(SCALE), atol=1e-5, rtol=0, msg=name)


def _scaled_scene(tmp_path, scale: float, offset=(0.0, 0.0, 0.0)):
    """The tiny test scene with its world scaled and moved (camera positions only: the same images)."""
    root = write_tiny_scene(tmp_path / f"scene_{scale}")
    for split in ("train", "val", "test"):
        path = root / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for f in meta["frames"]:
            for i in range(3):
                f["transform_matrix"][i][3] = scale * f["transform_matrix"][i][3] + offset[i]
        path.write_text(json.dumps(meta))
    return root


def _frame(scene, **kw):
    cfg = make_config("tiny", data=scene, device="cpu", **kw)
    return field_frame(cfg, ViewDataset(scene, "train", device="cpu"))


def test_auto_keeps_the_world_frame_for_a_blender_sized_scene_and_moves_any_other(tmp_path):
    center, scale = _frame(write_tiny_scene(tmp_path / "scene"))  # cameras 3.35 from the origin
    assert scale == 1.0 and (center == 0).all()
    center, scale = _frame(_scaled_scene(tmp_path, 10.0, (50.0, -20.0, 3.0)))
    # the tiny scene's cameras look at the origin from 3.35 units: the moved ones at the offset, 33.5
    torch.testing.assert_close(center, torch.tensor([50.0, -20.0, 3.0]), atol=0.05, rtol=0)
    assert scale == pytest.approx(10 * math.hypot(3, 1.5) / 4.031, rel=2e-3)
    center, scale = _frame(_scaled_scene(tmp_path, 0.05))  # a table-top capture in metres
    assert scale == pytest.approx(0.05 * math.hypot(3, 1.5) / 4.031, rel=2e-3)
    assert _frame(_scaled_scene(tmp_path, 10.0), field_frame="world")[1] == 1.0
    assert _frame(write_tiny_scene(tmp_path / "again"), field_frame="cameras")[1] != 1.0


def test_a_run_keeps_its_frame_and_older_checkpoints_load_in_the_world_frame(tmp_path):
    scene = _scaled_scene(tmp_path, 10.0, (50.0, -20.0, 3.0))
    cfg = make_config("tiny", data=scene, run=tmp_path / "run", device="cpu", init_points=200)
    trainer = Trainer(cfg, progress=False)
    trainer.train()
    loaded = load_run(tmp_path / "run", device="cpu")
    model = loaded.model
    torch.testing.assert_close(model.field_center, trainer.model.field_center)
    assert float(model.field_scale) == float(trainer.model.field_scale) > 1
    assert torch.isfinite(loaded.predictor.gaussians_at(1.3)["means"]).all()
    ckpt = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    for key in ("field_center", "field_scale"):  # as written before the fields had a frame
        del ckpt["model"][key]
    torch.save(ckpt, tmp_path / "run" / "checkpoint.pt")
    model = load_run(tmp_path / "run", device="cpu").model
    assert float(model.field_scale) == 1.0 and (model.field_center == 0).all()
    assert (
        model.fields_see_world and model.to_field_frame(model.gaussians["means"]) is model.gaussians["means"]
    )
