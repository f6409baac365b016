"""A diagnosis, not a setting: a run's future scored as learned and with some of f_trd's rates
(accelerations, angular accelerations, jerks) set to zero at render time, the run unchanged.
Tells which learned rate a future's error comes from (docs/PHYSICS.md, "The accelerations from their
own MLP").
Usage: .venv/bin/python benchmarks/without_rates.py [--future-end 0.7627] [--zero NAME ... --]
    [--spin-above W | --spin-below W] RUN ...
(--spin-above / --spin-below: zero them only where f_trd's |w| is above / at most W, e.g. a fan's
blades against its body.)
"""

import argparse
from unittest import mock

import torch

from tracegs.eval.protocol import evaluate_run
from tracegs.models.dynamics import ACCELERATIONS, DynamicsField


def score(
    run: str, future_end: float | None, zero: list[str], spin: tuple[str, float] | None = None
) -> float:
    """The run's extrapolation PSNR with the named outputs of f_trd zeroed (where ``spin`` = ("above"
    or "below", W) says: the particles whose |w| is above W, or at most W)."""
    learned = DynamicsField.outputs

    def outputs(self, x, t, rates=True):
        out = learned(self, x, t, rates)
        where = torch.ones_like(out["angular_velocity"][:, :1], dtype=torch.bool)
        if spin is not None:
            fast = out["angular_velocity"].norm(dim=-1, keepdim=True) > spin[1]
            where = fast if spin[0] == "above" else ~fast
        return {k: torch.where(where, 0.0, v) if k in zero else v for k, v in out.items()}

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
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--spin-above", type=float, default=None, help="zero them only where |w| > W")
    where.add_argument("--spin-below", type=float, default=None, help="zero them only where |w| <= W")
    args = parser.parse_args()
    spin = None
    if args.spin_above is not None or args.spin_below is not None:
        spin = ("above", args.spin_above) if args.spin_above is not None else ("below", args.spin_below)
    zeroed = " + ".join(args.zero) + " zeroed" + ("" if spin is None else f" where |w| {spin[0]} {spin[1]}")
    print(f"| run | learned | {zeroed} |\n|---|---|---|")
    for run in args.runs:
        learned, without = score(run, args.future_end, []), score(run, args.future_end, args.zero, spin)
        print(f"| {run} | {learned:.2f} | {without:.2f} |")


if __name__ == "__main__":
    main()
