"""Mask-based initialisation: on a small generated capture with foreground masks the visual hull puts
the initial Gaussians of the foreground inside the object; without masks the init stays random."""

from __future__ import annotations

import imageio.v2 as imageio
import numpy as np
import pytest
import torch

from tracegs.config import make_config
from tracegs.data.synth import synthesize
from tracegs.train.init import initial_gaussians


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A generated scene with ``masks/`` (foreground = any part) beside its training images."""
    root = synthesize("fallingball", tmp_path_factory.mktemp("hull") / "s", resolution=32, views=15,
                      frames=4, progress=False, spp=1)  # fmt: skip
    for path in (root / "gt" / "masks" / "train").glob("*.png"):
        out = root / "masks" / "train" / path.name
        out.parent.mkdir(parents=True, exist_ok=True)
        imageio.imwrite(out, ((imageio.imread(path) > 0) * 255).astype(np.uint8))
    return root


def test_the_hull_puts_the_initial_gaussians_inside_the_object(capture):
    cfg = make_config(
        "tiny", data=capture, run=capture / "run", init_points=50, init_hull=True, hull_resolution=48
    )
    aabb = torch.tensor([[-1.3] * 3, [1.3] * 3])
    said = []
    g = initial_gaussians(cfg, aabb, "cpu", log=said.append)
    means = g["means"].detach()
    hull = means[: len(means) - 50]
    assert len(hull) > 100 and "visual hull" in said[0]
    surface = torch.as_tensor(np.load(capture / "gt" / "points.npz")["points"], dtype=torch.float32)
    lo, hi = surface.min(0).values, surface.max(0).values
    step = 2.6 / 48
    # inside the objects' box, but below the ground: no camera sees under it, so no mask carves it away
    assert ((hull[:, :2] >= lo[:2] - 2 * step) & (hull[:, :2] <= hi[:2] + 2 * step)).all()
    assert (hull[:, 2] <= hi[2] + 2 * step).all()
    assert float(torch.cdist(surface, hull).min(1).values.max()) < 2.5 * step  # and it holds all of them
    assert set(g) == {"means", "quats", "scales", "opacities", "sh0", "shN"} and g["sh0"].shape[0] == len(
        means
    )


def test_without_masks_the_init_stays_random(capture, tmp_path):
    import shutil

    bare = tmp_path / "bare"
    shutil.copytree(capture, bare, ignore=shutil.ignore_patterns("masks"))
    cfg = make_config("tiny", data=bare, run=bare / "run", init_points=50, init_hull=True)
    said = []
    g = initial_gaussians(cfg, torch.tensor([[-1.3] * 3, [1.3] * 3]), "cpu", log=said.append)
    assert len(g["means"]) == 50 and "random" in said[0]


def test_a_training_starts_from_the_hull(capture, tmp_path):
    from tracegs.train.trainer import Trainer

    cfg = make_config(
        "tiny", data=capture, run=tmp_path / "run", init_points=50, init_hull=True, hull_resolution=32
    )
    trainer = Trainer(cfg, progress=False)
    assert trainer.model.gaussians["means"].shape[0] > 50
    trainer.train()
    assert (tmp_path / "run" / "summary.json").is_file()
