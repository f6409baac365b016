"""TRACE vs DefGS, or the ablations of the paper's Table 4, on the D-NeRF scenes of ../shared/data
(monocular; train on time <= 0.75).

Usage: .venv/bin/python benchmarks/dnerf.py [--scenes bouncingballs] [--downscale 2] [--preset cpu-fast]
           [--methods TRACE DefGS | --ablations order=1 "no physics derivation" ...] [--validation 0.8]
The data is not part of the repository (see ../shared/data/README.md).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tracegs.bench import ABLATIONS, METHODS, OPTIONS, run_variant_table


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument(
        "--root", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data" / "dnerf"
    )
    ap.add_argument("--scenes", nargs="+", default=["bouncingballs"])
    ap.add_argument("--downscale", type=int, default=2)
    ap.add_argument("--preset", default="cpu-fast")
    ap.add_argument("--methods", nargs="+", default=["TRACE", "DefGS"], choices=sorted(METHODS))
    ap.add_argument(
        "--ablations",
        nargs="+",
        choices=sorted(ABLATIONS | OPTIONS),
        help="rows of the ablation table (dnerf-ablations) instead of the method table; the paper's "
        'switches or our options (e.g. "12k dynamic")',
    )
    ap.add_argument(
        "--validation",
        type=float,
        help="train on this fraction of the training span and score its later frames (choosing settings)",
    )
    ap.add_argument("--out", type=Path, default=Path("runs/bench"))
    ap.add_argument("--json", type=Path, help="write the results record here (e.g. docs/results/dnerf.json)")
    args = ap.parse_args()
    scenes = tuple(str(args.root / s) for s in args.scenes)
    missing = [s for s in scenes if not Path(s, "transforms_train.json").is_file()]
    if missing:
        raise SystemExit(f"D-NeRF scene(s) not found: {', '.join(missing)}")
    if args.ablations:
        table, variants = "dnerf-ablations", {a: (ABLATIONS | OPTIONS)[a] for a in args.ablations}
        rows_flag = "--ablations " + " ".join(f'"{a}"' if " " in a else a for a in args.ablations)
    else:
        table, variants = "dnerf", {m: METHODS[m] for m in args.methods}
        rows_flag = "--methods " + " ".join(args.methods)
    overrides = {"downscale": args.downscale, "t_train_end": 0.75}
    command = (
        f"benchmarks/dnerf.py --scenes {' '.join(args.scenes)} --downscale {args.downscale} "
        f"--preset {args.preset} {rows_flag}"
        + ("" if args.validation is None else f" --validation {args.validation:g}")
    )
    rows = run_variant_table(
        table,
        variants,
        args.out,
        scenes,
        args.preset,
        800 // (2 * args.downscale),
        overrides,
        command=command,
        validation=args.validation,
        json_path=args.json,
    )
    future = "val_future_psnr" if args.validation is not None else "extrap_psnr"
    for r in rows:
        print(r["scene"], r["variant"], f"interp {r['interp_psnr']:.2f} dB", f"{future} {r[future]:.2f} dB")


if __name__ == "__main__":
    main()
