"""Time of a training step's fields (``TraceModel.training_state`` and its losses, forward and backward)
with each ``dynamic.consistency_transport``, on a trained run, in alternating rounds (median step of
each round, ``tracegs.bench._time``).

Usage: .venv/bin/python benchmarks/consistency_cost.py RUN [--rounds 3] [--steps 40]
"""

import argparse

from tracegs.bench import _time
from tracegs.train.trainer import load_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    model = load_run(args.run, device="cpu")[0]
    dt = 1 / 59  # a 60-frame scene's frame interval; the cost does not depend on it
    t_prime, t, t_check = 0.3, 0.3 + 2 * dt, 0.3 + 8 * dt

    def step() -> None:
        state, losses = model.training_state(t_prime, t, t_check=t_check)
        (state["means"].sum() + sum(losses.values())).backward()

    times: dict[str, list[float]] = {}
    for _ in range(args.rounds):
        for mode in ("dynamics", "deformation"):
            model.cfg.dynamic.consistency_transport = mode
            times.setdefault(mode, []).append(_time(step, repeats=args.steps))
    n = model.gaussians["means"].shape[0]
    moving = n if model.static_mask is None else int((~model.static_mask).sum())
    print(f"{args.run}: {moving} of {n} Gaussians moving")
    for mode, values in times.items():
        print(f"  {mode:12s} " + " ".join(f"{v:.1f}" for v in values) + " ms per step")
    extra = sorted(d - s for d, s in zip(times["deformation"], times["dynamics"], strict=True))
    print(f"  deformation - dynamics, median over the paired rounds: {extra[len(extra) // 2]:+.1f} ms")


if __name__ == "__main__":
    main()
