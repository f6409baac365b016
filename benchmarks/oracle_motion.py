"""How much of a run's future error is the learned physics: its validation future scored twice, as
learned and with the ground-truth motion from the handover (synthetic scenes, ``gt/`` of `tracegs synth`).

The oracle takes the Gaussians where f_defo leaves them at the handover, as TRACE's extrapolation
does, gives each the rigid motion of the ground-truth part nearest to it (every Gaussian, also those
inside an object) and moves it, position and orientation, with that part's exact motion. What the
oracle still loses is the reconstruction at the handover (and the Gaussians given to the wrong part
where parts touch); what it gains over the learned future is what the physics costs. ``--parts``
gives the exact motion to the Gaussians of the named parts only (the others keep their learned future):
what each part's learned physics costs (a static part's exact motion holds its Gaussians still).

Usage: .venv/bin/python benchmarks/oracle_motion.py [--future-end 0.7627] RUN ... [--parts NAME ...]
RUN: a validation run (trained to a cut below the scene's own end, e.g. the `*_val0.8` runs of
`tracegs bench ablations --validation 0.8`), scored to ``--future-end``. Without it the test split is
scored: a diagnosis of a finished run, never a way to choose a setting. docs/PHYSICS.md, "What the
physics costs".
"""

import argparse
from pathlib import Path

import numpy as np
import torch

import tracegs.eval.protocol as protocol
from tracegs.eval.physics import _gt, _motions, assign_parts
from tracegs.physics.so3 import quat_multiply, quat_normalize, rotmat_to_quat


def with_ground_truth_motion(model, data: Path, only: list[str] | None = None):
    """Replace ``model.state_at`` after the handover by the exact motion of each Gaussian's nearest part
    (of the Gaussians whose nearest part is named in ``only``, when given; the others keep theirs)."""
    points, part_ids, transforms = _gt(data)
    parts = sorted(int(p) for p in np.unique(part_ids))
    names = [m["name"] for m in _motions(data)]
    unknown = sorted(set(only or []) - set(names))
    if unknown:
        raise ValueError(f"{data}/gt/motion.json: no part named {unknown}; its parts are {names}")
    exact = [p for p in parts if only is None or names[p - 1] in only]
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
        future = state if only is None else learned(t, t_max)  # the other parts' Gaussians keep theirs
        means, quats = future["means"].clone(), quat_normalize(future["quats"]).clone()
        at_t = transforms(t)
        for p in exact:
            rows = owner == p
            rel = torch.as_tensor(at_t[p - 1] @ np.linalg.inv(start["at_t0"][p - 1]), dtype=means.dtype)
            means[rows] = state["means"][rows] @ rel[:3, :3].T + rel[:3, 3]
            turn = rotmat_to_quat(rel[:3, :3].to(means.device))[None].expand(int(rows.sum()), 4)
            quats[rows] = quat_multiply(turn, quat_normalize(state["quats"][rows]))
        return {"means": means, "quats": quats, "scales": state["scales"]}

    model.state_at = state_at
    return model


def _score(run: Path, future_end: float | None) -> dict:
    kw = {} if future_end is None else {"future_end": future_end}
    r = protocol.evaluate_run(run, with_lpips=False, save_images=False, device="cpu", **kw)
    e = r["extrapolation"]
    parts = {k: v["psnr"] for k, v in e.get("per_part", {}).items()}
    return {"psnr": e["psnr"], "mae_psnr": e["mae_psnr"], "parts": parts}


def score_replaced(run: Path, future_end: float | None, replace) -> tuple[dict, dict, str]:
    """(learned, replaced, per-part line) of a run's future: scored as learned, then with the model
    that ``replace(model, data)`` returns (e.g. ``with_ground_truth_motion``) in place of the loaded one."""
    learned = _score(run, future_end)
    load_run = protocol.load_run

    def replaced_load(*a, **k):
        model, cfg, meta = load_run(*a, **k)
        return replace(model, Path(cfg.data)), cfg, meta

    protocol.load_run = replaced_load
    try:
        replaced = _score(run, future_end)
    finally:
        protocol.load_run = load_run
    parts = " ".join(f"{n} {learned['parts'][n]:.2f}/{replaced['parts'][n]:.2f}" for n in learned["parts"])
    return learned, replaced, parts


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument(
        "--future-end", type=float, default=None, help="validation future's end (default: the test split)"
    )
    ap.add_argument(
        "--parts", nargs="+", default=None, help="exact motion for these parts only (gt/motion.json names)"
    )
    args = ap.parse_args()
    for run in args.runs:
        learned, oracle, parts = score_replaced(
            run, args.future_end, lambda model, data: with_ground_truth_motion(model, data, args.parts)
        )
        print(
            f"{run.name}: learned {learned['psnr']:.3f} dB (MAE-PSNR {learned['mae_psnr']:.3f}), exact motion "
            f"{oracle['psnr']:.3f} ({oracle['mae_psnr']:.3f}); parts {parts}"
        )


if __name__ == "__main__":
    main()
