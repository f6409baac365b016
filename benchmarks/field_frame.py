"""A scene in other units or far from the origin, with the fields in the world's frame and in the
cameras' (docs/DESIGN.md, "Training"; docs/BENCHMARKS.md, "The fields' frame").

Writes copies of a Blender-format scene whose world is scaled (and moved): the same images, the
cameras' positions mapped, the json's ``aabb`` dropped as a capture would have none. Trains each
with ``cpu-fast`` shortened to ``--static`` + ``--dynamic`` steps up to ``--t-train-end`` and scores
the validation future (the training cameras up to ``--future-end``) and interpolation.

Usage: .venv/bin/python benchmarks/field_frame.py SCENE --out DIR [--static 500 --dynamic 3000]
"""

import argparse
import json
import os
from pathlib import Path

from tracegs.config import make_config
from tracegs.eval.protocol import evaluate_run
from tracegs.train.trainer import Trainer

# name: (scale, offset, field frames to train with)
COPIES = {
    "x1": (1.0, (0.0, 0.0, 0.0), ("auto", "cameras")),
    "x10_moved": (10.0, (50.0, -20.0, 3.0), ("world", "auto")),
    "x0.1": (0.1, (0.0, 0.0, 0.0), ("world", "auto")),
}


def scaled_copy(scene: Path, out: Path, scale: float, offset) -> Path:
    out.mkdir(parents=True, exist_ok=True)
    for name in os.listdir(scene):
        if (scene / name).is_dir() and not (out / name).exists():
            os.symlink((scene / name).resolve(), out / name)
    for path in scene.glob("transforms_*.json"):
        meta = json.loads(path.read_text())
        meta.pop("aabb", None)
        for f in meta["frames"]:
            for i in range(3):
                f["transform_matrix"][i][3] = scale * f["transform_matrix"][i][3] + offset[i]
        (out / path.name).write_text(json.dumps(meta))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene", type=Path)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--static", type=int, default=500)
    ap.add_argument("--dynamic", type=int, default=3000)
    ap.add_argument("--t-train-end", type=float, default=0.6101694915254238)
    ap.add_argument("--future-end", type=float, default=0.7627118644067796)
    args = ap.parse_args()
    for name, (scale, offset, frames) in COPIES.items():
        data = scaled_copy(args.scene, args.out / "scenes" / name, scale, offset)
        for frame in frames:
            run = args.out / "runs" / f"{name}_{frame}"
            cfg = make_config(
                "cpu-fast",
                data=data,
                run=run,
                static_iterations=args.static,
                dynamic_iterations=args.dynamic,
                t_train_end=args.t_train_end,
                field_frame=frame,
            )
            summary = Trainer(cfg, progress=False).train()
            r = evaluate_run(
                run, with_lpips=False, save_images=False, future_end=args.future_end, device="cpu"
            )
            print(
                f"{name} fields in the {frame} frame: validation future {r['extrapolation']['mae_psnr']:.2f}, "
                f"interpolation {r['interpolation']['mae_psnr']:.2f}, {summary['train_seconds']:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
