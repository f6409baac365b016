"""An exported sequence rendered back: `tracegs export --times` writes a run's Gaussians as numbered 3DGS
PLY files, which are read back and rendered from a dataset camera beside the run's own render at the
same times (docs/figures/export/rendered_back.png: top row the run, bottom row the re-read PLY files;
columns the times, those past the training span predicted). Prints the largest pixel difference.

Usage: .venv/bin/python benchmarks/export_figure.py RUN [--data SCENE] [--times 0:1.5:0.5]
       [--camera test:0] [--out docs/figures/export/rendered_back.png]
(RUN: a trained run, e.g. of `tracegs train --data data/fan --run runs/fan --preset cpu-fast`.)
"""

from __future__ import annotations

import argparse
import copy
import json
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from tracegs.data.scene import load_scene
from tracegs.export.command import export_run
from tracegs.export.ply import read_gaussians
from tracegs.export.render import pick_camera
from tracegs.extrapolate import Predictor
from tracegs.run import load_run
from tracegs.utils import atomic_write_image

GAP = 4
"""White pixels between the images of the strip."""


def with_gaussians(model, params: dict[str, torch.Tensor]):
    """A copy of ``model`` whose Gaussians are ``params`` (read back from a PLY)."""
    other = copy.deepcopy(model)
    other.gaussians = nn.ParameterDict({k: nn.Parameter(v.clone()) for k, v in params.items()})
    return other


def strip(rows: list[list[np.ndarray]]) -> np.ndarray:
    """The images [H, W, 3] of ``rows`` side by side, rows stacked, GAP white pixels between them."""
    h, w, _ = rows[0][0].shape
    out = np.ones((len(rows) * (h + GAP) - GAP, len(rows[0]) * (w + GAP) - GAP, 3))
    for i, row in enumerate(rows):
        for j, image in enumerate(row):
            out[i * (h + GAP) : i * (h + GAP) + h, j * (w + GAP) : j * (w + GAP) + w] = image
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--data", type=Path, default=None, help="the scene (default: the run's)")
    parser.add_argument("--times", default="0:1.5:0.5")
    parser.add_argument("--camera", default="test:0")
    parser.add_argument("--out", type=Path, default=Path("docs/figures/export/rendered_back.png"))
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args()
    loaded = load_run(args.run, args.device)
    cfg = loaded.config
    data = args.data or cfg.data
    predictor = loaded.predictor.with_background(load_scene(data, "train").background)
    dev = predictor.device
    camera = pick_camera(data, args.camera, cfg.downscale).to(dev)
    with tempfile.TemporaryDirectory() as folder:
        report = export_run(args.run, times=args.times, out=folder, device=args.device)
        index = json.loads(Path(report["index"]).read_text())
        own, back = [], []
        for t, name in zip(index["times"], index["files"]["ply"], strict=True):
            params = read_gaussians(Path(folder) / name, dev)
            own.append(predictor.render(camera, t).cpu().numpy())
            reloaded = Predictor(
                with_gaussians(predictor.model, params), predictor.state, background=predictor.background
            )
            back.append(reloaded.render(camera, gaussians=params).cpu().numpy())
    diff = max(float(np.abs(a - b).max()) for a, b in zip(own, back, strict=True))
    atomic_write_image(args.out, strip([own, back]))
    predicted = [f"{t:g}" for t, p in zip(index["times"], index["predicted"], strict=True) if p]
    print(
        f"{args.out}: times {', '.join(f'{t:g}' for t in index['times'])} (predicted: {', '.join(predicted)}; "
        f"t_max {index['t_max']:.3f}), {report['gaussians']} Gaussians; largest pixel difference between "
        f"the run's render and the re-read PLY's: {diff:.3g} ({255 * diff:.3g} of 255)"
    )


if __name__ == "__main__":
    main()
