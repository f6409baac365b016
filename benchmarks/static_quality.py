"""Static 3DGS (the paper's first stage) on a generated scene at t = 0: PSNR on held-out views.

Renders a synthetic scene with `--views` cameras (two frames; only t = 0 is used), trains
`--method static` on the training cameras and scores the held-out (val) cameras, as static 3DGS
benchmarks do (NeRF-synthetic has 100 training views; the dynamic protocol's 12 are too few for a
static scene). Usage: .venv/bin/python benchmarks/static_quality.py [--scene fan] [--views 40]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from tracegs.config import make_config
from tracegs.data.scene import load_image, load_scene
from tracegs.data.synth import synthesize
from tracegs.eval.metrics import mae_psnr, mse, ssim
from tracegs.results import make_record, write_record
from tracegs.run import load_run
from tracegs.train.trainer import Trainer


def record_notes(scene: str, views: int) -> str:
    """The record's notes: the render the row is trained and scored on (``views`` cameras of ``scene``)."""
    return (
        f"Static 3DGS on a {views}-view render of `{scene}` at t = 0, trained on its training cameras and "
        "scored on the held-out ones (`heldout_views`)."
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", default="fan")
    ap.add_argument("--preset", default="cpu-fast")
    ap.add_argument("--iterations", type=int, default=3000)
    ap.add_argument("--views", type=int, default=40)
    ap.add_argument("--out", type=Path, default=Path("runs/bench"))
    ap.add_argument(
        "--json", type=Path, help="write the results record here (docs/results/static-quality.json)"
    )
    args = ap.parse_args()
    data = args.out / "scenes" / f"{args.scene}_128_static_v{args.views}"
    if not (data / "transforms_val.json").is_file():
        synthesize(
            args.scene, data, resolution=128, views=args.views, frames=2, train_frames=1, progress=False
        )
    run = args.out / "runs" / f"{args.scene}_static_{args.preset}"
    cfg = make_config(args.preset, data=data, run=run, method="static", static_iterations=args.iterations)
    summary = Trainer(cfg, progress=False).train()
    loaded = load_run(run, "cpu")
    scene = load_scene(data, "val")
    predictor = loaded.predictor.with_background(scene.background)
    mses, ssims = [], []
    for f in scene.frames:
        if f.time != 0.0:
            continue
        pred = predictor.render(f.camera, 0.0)
        gt = load_image(f, scene.background)
        mses.append(float(mse(pred, gt)))
        ssims.append(float(ssim(pred, gt)))
    row = {
        "scene": args.scene,
        "preset": args.preset,
        "iterations": summary["iterations"],
        "gaussians": summary["gaussians"],
        "heldout_views": len(mses),
        "psnr": mae_psnr(mses),
        "ssim": sum(ssims) / len(ssims),
        "train_s": summary["train_seconds"],
    }
    print(json.dumps(row, indent=2))
    if args.json is not None:
        command = (
            f".venv/bin/python benchmarks/static_quality.py --scene {args.scene} --views {args.views} "
            f"--preset {args.preset} --iterations {args.iterations} --json {args.json}"
        )
        title = "Static reconstruction (stage 1) on a generated scene, held-out views at t = 0"
        notes = record_notes(args.scene, args.views)
        write_record(args.json, make_record("static-quality", [row], command, title=title, notes=notes))


if __name__ == "__main__":
    main()
