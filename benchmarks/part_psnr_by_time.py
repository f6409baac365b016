"""PSNR of each ground-truth part of a synthetic scene, time by time, over a split's cameras.

Tells a part's reconstruction error from its motion error: a part that is already poor at t = 0 on the
training cameras (where stage 1 fitted it) is limited by its reconstruction, one that degrades with time
by its motion. Uses the scene's ``gt/masks`` (part id of each pixel) and the evaluation's rendering.
Usage: .venv/bin/python benchmarks/part_psnr_by_time.py RUN [--split train|val] [--every K]
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from pathlib import Path

import torch

from tracegs.data.blender import load_image, load_scene
from tracegs.eval.metrics import mae_psnr
from tracegs.eval.protocol import PartErrors, part_names
from tracegs.train.trainer import load_run


@torch.no_grad()
def part_psnr_by_time(run: Path, split: str = "val") -> dict[float, dict[str, float]]:
    """{time: {part name: PSNR over that part's pixels in every camera of ``split`` at that time}}."""
    model, cfg, meta = load_run(run, device="cpu")
    data = Path(cfg.data)
    names = part_names(data)
    if not names:
        raise ValueError(f"{data}: no gt/masks and gt/motion.json; part PSNRs need a `tracegs synth` scene")
    scene = load_scene(data, split, cfg.downscale)
    background = torch.tensor(scene.background)
    frames_at: dict[float, list] = defaultdict(list)
    for f in scene.frames:
        frames_at[f.time].append(f)
    by_time: dict[float, PartErrors] = {}
    for t in sorted(frames_at):
        state = model.state_at(t, meta["t_max"])  # once per time, for all of its cameras
        errors = by_time[t] = PartErrors(names)
        for f in frames_at[t]:
            pred = model.render(state, f.camera, cfg.sh_degree, background).image.clamp(0, 1)
            errors.add(
                pred, load_image(f, scene.background), data / "gt" / "masks" / split / f.image_path.name
            )
    return {
        t: {name: mae_psnr([float(e.error[i] / e.pixels[i])]) for i, name in names.items() if e.pixels[i] > 0}
        for t, e in by_time.items()
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--split", default="val", choices=("train", "val", "test"))
    parser.add_argument("--every", type=int, default=5, help="print every K-th time")
    args = parser.parse_args()
    rows = list(part_psnr_by_time(args.run, args.split).items())
    for t, parts in rows[:: args.every] + ([rows[-1]] if (len(rows) - 1) % args.every else []):
        print(f"t={t:.3f} " + " ".join(f"{name} {psnr:.1f}" for name, psnr in parts.items()))


if __name__ == "__main__":
    main()
