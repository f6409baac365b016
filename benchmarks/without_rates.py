"""A diagnosis, not a setting: a run's future scored as learned and with some of f_trd's rates
(accelerations, angular accelerations, jerks) set to zero at render time, the run unchanged.
Tells which learned rate a future's error comes from (docs/PHYSICS.md, "The accelerations from their
own MLP").
Usage: .venv/bin/python benchmarks/without_rates.py [--future-end 0.7627] [--zero angular_acceleration] RUN ...
"""

import argparse
from unittest import mock

import torch

from tracegs.eval.protocol import evaluate_run
from tracegs.models.dynamics import ACCELERATIONS, DynamicsField


def score(run: str, future_end: float | None, zero: list[str]) -> float:
    """The run's extrapolation PSNR with the named outputs of f_trd zeroed."""
    learned = DynamicsField.outputs

    def outputs(self, x, t, rates=True):
        out = learned(self, x, t, rates)
        return {k: torch.zeros_like(v) if k in zero else v for k, v in out.items()}

    kw = {} if future_end is None else {"future_end": future_end}
    with mock.patch.object(DynamicsField, "outputs", outputs):
        r = evaluate_run(run, with_lpips=False, save_images=False, device="cpu", **kw)
    return r["extrapolation"]["psnr"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    parser.add_argument("runs", nargs="+")
    parser.add_argument(
        "--future-end", type=float, default=None, help="validation future's end (default: the test split)"
    )
    parser.add_argument("--zero", nargs="+", default=["angular_acceleration"], choices=ACCELERATIONS)
    args = parser.parse_args()
    print(f"| run | learned | {' + '.join(args.zero)} zeroed |\n|---|---|---|")
    for run in args.runs:
        print(
            f"| {run} | {score(run, args.future_end, []):.2f} | {score(run, args.future_end, args.zero):.2f} |"
        )


if __name__ == "__main__":
    main()
