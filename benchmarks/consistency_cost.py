"""Time of a training step's fields (``TraceModel.training_state`` and its losses, forward and backward)
with each ``dynamic.consistency_transport``, on a trained run, in alternating rounds.

Usage: .venv/bin/python benchmarks/consistency_cost.py RUN [--rounds 3] [--steps 40]
"""

import argparse
import time

from tracegs.train.trainer import load_run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    model, cfg, _ = load_run(args.run, device="cpu")
    dt = 1 / 59  # a 60-frame scene's frame interval; the cost does not depend on it
    t_prime, t, t_check = 0.3, 0.3 + 2 * dt, 0.3 + 8 * dt
    times: dict[str, list[float]] = {}
    for _ in range(args.rounds):
        for mode in ("dynamics", "deformation"):
            model.cfg.dynamic.consistency_transport = mode
            for _ in range(5):  # warm-up
                model.training_state(t_prime, t, t_check=t_check)
            start = time.perf_counter()
            for _ in range(args.steps):
                state, losses = model.training_state(t_prime, t, t_check=t_check)
                (state["means"].sum() + sum(losses.values())).backward()
            times.setdefault(mode, []).append((time.perf_counter() - start) / args.steps * 1e3)
    rows = model._moving_rows()
    moving = model.gaussians["means"].shape[0] if rows is None else rows.numel()
    print(f"{args.run}: {moving} of {model.gaussians['means'].shape[0]} Gaussians moving")
    for mode, values in times.items():
        print(f"  {mode:12s} " + " ".join(f"{v:.1f}" for v in values) + " ms per step")


if __name__ == "__main__":
    main()
