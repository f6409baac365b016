"""PSNR against future time for several evaluated runs, and a GT | run | run image strip.

Usage: .venv/bin/python benchmarks/horizon_plot.py --out docs/figures/fan LABEL=RUN [LABEL=RUN ...]
(each RUN evaluated with `tracegs eval` and its frames saved, the default).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from tracegs.config import load_config
from tracegs.export.plots import horizon_plot, image_strip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("runs", nargs="+", help="LABEL=RUN_FOLDER")
    ap.add_argument("--out", type=Path, required=True, help="output prefix (…_horizon.png, …_strip.png)")
    ap.add_argument("--camera", type=int, default=0)
    ap.add_argument("--error-gain", type=float, default=0.0, help="add |run - GT| x this under each run")
    args = ap.parse_args()
    runs = dict(item.split("=", 1) for item in args.runs)
    runs = {k: Path(v) for k, v in runs.items()}
    data = Path(load_config(next(iter(runs.values())) / "config.json").data)
    print(horizon_plot(runs, Path(f"{args.out}_horizon.png"), title=data.name))
    print(
        image_strip(
            data, runs, Path(f"{args.out}_strip.png"), camera_id=args.camera, error_gain=args.error_gain
        )
    )


if __name__ == "__main__":
    main()
