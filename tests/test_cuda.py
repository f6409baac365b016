"""The CUDA path against the CPU path. Skipped without CUDA (CI has none); run on a GPU machine with
``pytest tests/test_cuda.py tests/render/test_render_api.py``.

Training on CUDA renders with gsplat, on CPU with the native or reference rasteriser; the fields are
the same PyTorch modules (the HexPlane's sampling is grid_sample on CUDA, a C++ kernel on CPU). A run
trained on one device must give the same Gaussians and images on the other.
"""

import copy

import pytest
import torch

from tests.conftest import randomised_model
from tests.render.render_helpers import PARAMS, hard_scene, native_available, rel_err, render_with_grads
from tracegs.config import apply_overrides, make_config
from tracegs.data.dataset import ViewDataset
from tracegs.extrapolate import ExtrapolationState, Predictor
from tracegs.run import load_run
from tracegs.train.trainer import Trainer

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

VARIANTS = [{}, {"method": "defgs"}, {"deformation.kind": "hexplane"}]
VARIANT_IDS = ["trace", "defgs", "trace_4dgs"]


def test_reference_backend_on_cuda_matches_cpu():
    """The fallback when gsplat's kernels cannot be loaded: the pure-PyTorch rasteriser on CUDA."""
    scene = hard_scene(500, 40, 32, seed=3, sh_degree=1)
    cpu = render_with_grads(scene, "reference")
    gpu = render_with_grads({k: v.cuda() if torch.is_tensor(v) else v for k, v in scene.items()}, "reference")
    for key in ("image", "alpha", "depth"):  # float32 sums in another order
        assert (gpu[key].cpu() - cpu[key]).abs().max() < 1e-5, key
    for name in [*PARAMS, "means2d"]:
        assert rel_err(gpu["grad_" + name].cpu(), cpu["grad_" + name]) < 1e-4, name


@pytest.mark.parametrize("frame", [None, (0.3, -0.2, 0.1, 2.5)], ids=["world", "camera_frame"])
@pytest.mark.parametrize("switch", VARIANTS[::2], ids=VARIANT_IDS[::2])
def test_fields_move_gaussians_the_same_on_cuda(switch, frame):
    # fp32 on both sides (the presets choose bf16 on CPUs with AMX, which would be the difference)
    cfg = apply_overrides(make_config("tiny", device="cpu", bf16=False), switch)
    cpu = randomised_model(cfg)
    if frame is not None:  # the fields see positions in a moved and scaled frame (scene_frame.py)
        cpu.set_field_frame(torch.tensor(frame[:3]), frame[3])
        assert not cpu.fields_see_world
    gpu = copy.deepcopy(cpu).cuda()
    with torch.no_grad():
        for name, (a, b) in {
            "training_state": (cpu.training_state(0.4, 0.45)[0], gpu.training_state(0.4, 0.45)[0]),
            "extrapolated": (
                Predictor(cpu, ExtrapolationState(t_max=0.75)).gaussians_at(1.3),
                Predictor(gpu, ExtrapolationState(t_max=0.75)).gaussians_at(1.3),
            ),
        }.items():
            assert not torch.allclose(a["means"], cpu.gaussians["means"], atol=1e-3), "fields do not move"
            for key in ("means", "quats", "scales"):
                assert rel_err(b[key].cpu(), a[key]) < 1e-4, (name, key)


@pytest.mark.parametrize("switch", VARIANTS, ids=VARIANT_IDS)
def test_run_trained_on_cuda_renders_the_same_on_cpu(tiny_scene, tmp_path, switch):
    run = tmp_path / "run"
    cfg = make_config(
        "tiny", data=tiny_scene, run=run, device="cuda", static_iterations=20, dynamic_iterations=20
    )
    cfg.init_points = 300
    summary = Trainer(apply_overrides(cfg, switch), progress=False).train()
    assert summary["iterations"] == 40
    assert summary["device"].startswith("cuda") and summary["rasteriser"] in ("gsplat", "reference")
    models = {dev: load_run(run, device=dev) for dev in ("cuda", "cpu")}
    assert models["cuda"].model.gaussians["means"].is_cuda
    images = {}
    for dev, loaded in models.items():
        views = ViewDataset(tiny_scene, "test", device=dev)
        images[dev] = [
            loaded.predictor.with_background(views.background).render(v.camera, v.time).cpu() for v in views
        ]
    for gpu, cpu in zip(images["cuda"], images["cpu"], strict=True):
        assert cpu.std() > 0.01  # something was rendered
        # gsplat against the CPU rasteriser: the same numerics up to gsplat's tile binning (see
        # tests/render/test_render_api.py), so a few pixels may differ by a barely visible alpha.
        assert (gpu - cpu).abs().max() < 3e-2
        assert (gpu - cpu).abs().mean() < 1e-3


def test_cuda_picks_gsplat_when_its_kernels_load():
    from tracegs.render import gsplat_backend
    from tracegs.render.rendering import resolve_backend

    expected = "gsplat" if gsplat_backend.is_available() else "reference"
    assert resolve_backend("auto", torch.device("cuda")) == expected
    assert resolve_backend("auto", torch.device("cpu")) == ("native" if native_available() else "reference")
