"""Sizes of what f_trd has learned, for any trained TRACE run (no ground truth needed).

Prints, at a few training times and at the handover t0, the median over all Gaussians of |x| and of
the norm of each of f_trd's named outputs (``DynamicsField.outputs``: v_bar, w, a_bar, eps; for the
"no equivalence" variant the explicit centre P_c, its velocity v_c and acceleration a_c, |x - P_c|
and the v_bar, a_bar they convert to), then the median displacement the physics predicts from t0 to
``--future`` beside the one f_defo reconstructed over the same span before t0. A learned motion far larger than the
reconstructed one is what an extrapolation that flies apart looks like (docs/PHYSICS.md, "Why the
explicit centre fails on standup"). Positions and f_trd's outputs are in the fields' frame
(``TraceModel.set_field_frame``): the world's for Blender-sized scenes.
Usage: .venv/bin/python benchmarks/dynamics_magnitudes.py RUN [RUN ...] [--future 1.0]
"""

import argparse
from pathlib import Path

import torch

from tracegs.train.trainer import load_run


def _median_norm(x: torch.Tensor) -> float:
    return x.norm(dim=-1).median().item()


@torch.no_grad()
def report(run: Path, future: float) -> None:
    model, _, meta = load_run(run, device="cpu")
    if model.dynamics is None:
        raise SystemExit(f"{run}: not a TRACE run (it has no dynamics field)")
    t_max = meta["t_max"]
    t0 = model.handover_time(t_max)
    print(f"{run}: t_max {t_max:.3f}, handover t0 {t0:.3f}, {model.gaussians['means'].shape[0]} Gaussians")
    for t in (0.25 * t0, 0.5 * t0, t0):
        means = model.to_field_frame(model.deform(t)["means"])  # the values as f_trd reads them
        with model.autocast():
            named = {name: v.float() for name, v in model.dynamics.outputs(means, t).items()}
        sizes = {name: _median_norm(v) for name, v in named.items()}
        if "center" in named:  # and the equivalent parameters they convert to (Eq. 5)
            params = model.dynamics.params(named)
            sizes["x - center"] = _median_norm(means - named["center"])
            sizes["v_bar"], sizes["a_bar"] = _median_norm(params.velocity), _median_norm(params.acceleration)
        print(
            f"  t={t:.3f} |x| {_median_norm(means):.3f} "
            + " ".join(f"|{k}| {v:.3f}" for k, v in sizes.items())
        )
    at_t0 = means  # the loop's last time is t0
    span = future - t0
    predicted = model.state_at(future, t_max)["means"] - at_t0
    reconstructed = at_t0 - model.deform(max(0.0, t0 - span))["means"]
    print(
        f"  displacement over {span:.3f}: predicted t0 -> {future:g} {_median_norm(predicted):.4f}, "
        f"f_defo's {max(0.0, t0 - span):.3f} -> t0 {_median_norm(reconstructed):.4f} (medians)"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--future", type=float, default=1.0, help="the future time to predict (default 1.0)")
    args = ap.parse_args()
    for run in args.runs:
        report(run, args.future)


if __name__ == "__main__":
    main()
