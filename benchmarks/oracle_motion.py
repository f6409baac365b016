"""How much of a run's future error is the learned physics: its validation future scored twice, as
learned and with the ground-truth motion from the handover (synthetic scenes, ``gt/`` of `tracegs synth`).

The oracle takes the Gaussians where f_defo leaves them at the handover, as TRACE's extrapolation
does, gives each the rigid motion of the ground-truth part nearest to it (every Gaussian, also those
inside an object) and moves it, position and orientation, with that part's exact motion. What the
oracle still loses is the reconstruction at the handover (and the Gaussians given to the wrong part
where parts touch); what it gains over the learned future is what the physics costs.

Usage: .venv/bin/python benchmarks/oracle_motion.py --future-end 0.7627 RUN [RUN ...]
RUN: a validation run (trained to a cut below the scene's own end, e.g. the `*_val0.8` runs of
`tracegs bench ablations --validation 0.8`); never the test split. docs/PHYSICS.md, "What the physics
costs".
"""

import argparse
from pathlib import Path

import numpy as np
import torch

import tracegs.eval.protocol as protocol
from tracegs.eval.physics import _gt, assign_parts
from tracegs.physics.so3 import quat_multiply, quat_normalize, rotmat_to_quat


def with_ground_truth_motion(model, data: Path):
    """Replace ``model.state_at`` after the handover by the exact motion of each Gaussian's nearest part."""
    points, part_ids, transforms = _gt(data)
    parts = sorted(int(p) for p in np.unique(part_ids))
    learned, start = model.state_at, {}

    def state_at(t: float, t_max: float) -> dict[str, torch.Tensor]:
        t0 = model.handover_time(t_max)
        if t <= t0:
            return learned(t, t_max)
        if not start:
            at_t0 = transforms(t0)
            world = np.concatenate(
                [points[part_ids == p] @ at_t0[p - 1][:3, :3].T + at_t0[p - 1][:3, 3] for p in parts]
            )
            ids = np.concatenate([part_ids[part_ids == p] for p in parts])
            state = model.deform(t0)
            start.update(
                state=state, at_t0=at_t0, owner=assign_parts(state["means"], world, ids, float("inf"))
            )
        state, owner = start["state"], start["owner"]
        means, quats = state["means"].clone(), quat_normalize(state["quats"]).clone()
        at_t = transforms(t)
        for p in parts:
            rows = owner == p
            rel = torch.as_tensor(at_t[p - 1] @ np.linalg.inv(start["at_t0"][p - 1]), dtype=means.dtype)
            means[rows] = means[rows] @ rel[:3, :3].T + rel[:3, 3]
            turn = rotmat_to_quat(rel[:3, :3].to(means.device))[None].expand(int(rows.sum()), 4)
            quats[rows] = quat_multiply(turn, quats[rows])
        return {"means": means, "quats": quats, "scales": state["scales"]}

    model.state_at = state_at
    return model


def _score(run: Path, future_end: float) -> dict:
    r = protocol.evaluate_run(run, with_lpips=False, save_images=False, future_end=future_end, device="cpu")
    e = r["extrapolation"]
    return {"psnr": e["mae_psnr"], "parts": {k: v["psnr"] for k, v in e.get("per_part", {}).items()}}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--future-end", type=float, required=True)
    args = ap.parse_args()
    load_run = protocol.load_run
    for run in args.runs:
        learned = _score(run, args.future_end)

        def oracle_load(*a, **k):
            model, cfg, meta = load_run(*a, **k)
            return with_ground_truth_motion(model, Path(cfg.data)), cfg, meta

        protocol.load_run = oracle_load
        try:
            oracle = _score(run, args.future_end)
        finally:
            protocol.load_run = load_run
        parts = " ".join(
            f"{name} {learned['parts'][name]:.2f}/{oracle['parts'][name]:.2f}" for name in learned["parts"]
        )
        print(
            f"{run.name}: learned {learned['psnr']:.3f} dB, exact motion {oracle['psnr']:.3f}; parts {parts}"
        )


if __name__ == "__main__":
    main()
