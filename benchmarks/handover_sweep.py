"""Validation-future PSNR of finished runs for several ``dynamic.handover_frames`` (a render-time
setting, so no retraining): docs/DESIGN.md, "Presets", and docs/BENCHMARKS.md, "Render-time settings".

Usage: .venv/bin/python benchmarks/handover_sweep.py --frames 1 2 4 8 --future-end 0.7627 RUN [RUN ...]
RUN: a validation run (`tracegs train ... --t-train-end T` below the scene's own end, e.g. the
`*_val0.8` runs of `tracegs bench ablations --validation 0.8`); scored with `evaluate_run(..., future_end)`.
"""

import argparse
from pathlib import Path

from tracegs.eval.protocol import evaluate_run


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--frames", nargs="+", type=float, default=[1, 2, 4, 8])
    ap.add_argument("--future-end", type=float, required=True)
    args = ap.parse_args()
    for run in args.runs:
        for frames in args.frames:
            r = evaluate_run(
                run,
                with_lpips=False,
                save_images=False,
                future_end=args.future_end,
                device="cpu",
                render_settings={"dynamic__handover_frames": frames},
            )
            print(
                f"{run.name} handover {frames:g}: future {r['extrapolation']['mae_psnr']:.2f} "
                f"interpolation {r['interpolation']['mae_psnr']:.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
