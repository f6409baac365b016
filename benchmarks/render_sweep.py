"""Validation-future PSNR of finished runs for several values of one render-time setting (no
retraining), e.g. ``dynamic__handover_frames`` or ``dynamic__hold_unseen``: docs/DESIGN.md, "Presets",
docs/PHYSICS.md and docs/BENCHMARKS.md, "Render-time settings".

Usage: .venv/bin/python benchmarks/render_sweep.py --setting dynamic__handover_frames --values 1 2 4 8
       --future-end 0.7627 RUN [RUN ...]
RUN: a validation run (`tracegs train ... --t-train-end T` below the scene's own end, e.g. the
`*_val0.8` runs of `tracegs bench ablations --validation 0.8`); scored with `evaluate_run(..., future_end)`.
The setting is named as in ``config.apply_overrides`` (section, double underscore, field).
"""

import argparse
from pathlib import Path

from tracegs.eval.protocol import evaluate_run


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--setting", default="dynamic__handover_frames")
    ap.add_argument("--values", nargs="+", type=float, default=[1, 2, 4, 8])
    ap.add_argument("--future-end", type=float, required=True)
    args = ap.parse_args()
    for run in args.runs:
        for value in args.values:
            r = evaluate_run(
                run,
                with_lpips=False,
                save_images=False,
                future_end=args.future_end,
                device="cpu",
                render_settings={args.setting: value},
            )
            print(
                f"{run.name} {args.setting} {value:g}: future {r['extrapolation']['mae_psnr']:.3f} "
                f"interpolation {r['interpolation']['mae_psnr']:.3f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
