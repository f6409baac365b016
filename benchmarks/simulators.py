"""Export to simulators, checked against the ground truth: for each trained run of a `tracegs synth`
scene, the run's MJCF (`tracegs export --mjcf`, `export/simulator.py`) run in MuJoCo from the
handover, and for each moving ground-truth part:

* the joint of the exported body that holds most of its Gaussians against the part's kind (a hinge for
  a part turning about a line, fixed or carried by another; a rail for a translation; a free or
  planar body for one in flight, rolling, sliding or precessing, a disc sliding on after an impact
  also a rail), the axis's angle to the truth's
  (degrees) and the pivot's distance from the true axis (percent of the scene size, the diagonal of
  the ground-truth surface's bounding box), in the exported parent's frame at the handover;
* the mean future path error of its Gaussians, MuJoCo's and the run's own extrapolation's, in percent
  of the scene size (`eval/physics.py`, the same Gaussians and times).

Usage: .venv/bin/python benchmarks/simulators.py RUN [RUN ...] [--json docs/results/simulators.json]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from tracegs.eval.physics import _gt, _parts_at, physics_errors
from tracegs.export.simulate import simulate
from tracegs.export.simulator import build_model
from tracegs.results import make_record, write_record
from tracegs.run import load_run

HINGE = {"rotation", "damped_rotation", "friction_stop", "hinged_chain", "carried", "rotation+translation"}
RAIL = {"translation", "damped_translation"}
COLUMNS = [
    "scene",
    "part",
    "truth",
    "joint",
    "joint_right",
    "axis_deg",
    "pivot_pct",
    "mujoco_path_pct",
    "run_path_pct",
]
NOTES = (
    "Each run's MJCF run in MuJoCo from the handover against the ground truth, per moving part; "
    "paths in percent of the scene size over the future, MuJoCo's beside the run's own."
)
TIMES = 8
DELTA = 0.01


def expected(kind: str) -> set[str]:
    if kind in HINGE:
        return {"hinge"}
    if kind == "translation":  # a drifting body: on a rail, or free
        return {"slide", "free"}
    if kind in RAIL:
        return {"slide"}
    if kind == "sliding_collision":  # after its impact a disc slides on along a line
        return {"free", "planar", "slide"}
    return {"free", "planar"}


def screw(D: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """``(direction [3], point [3] or None)`` of the small motion ``D`` [4, 4]: its rotation's axis and
    a point on it, or for a translation its direction and None."""
    R, t = D[:3, :3], D[:3, 3]
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    if np.linalg.norm(w) < 1e-9:
        return t / max(np.linalg.norm(t), 1e-300), None
    axis = w / np.linalg.norm(w)
    point = np.linalg.lstsq(np.eye(3) - R, t, rcond=None)[0]
    return axis, point - (point @ axis) * axis


def true_joint(transforms, k: int, parent: int | None, t0: float) -> tuple[np.ndarray, np.ndarray | None]:
    """Part ``k``'s joint at ``t0`` in the world, from its motion in the frame of part ``parent``."""

    def frame(t):
        T = transforms(t)
        return T[k] if parent is None else np.linalg.inv(T[parent]) @ T[k]

    D = frame(t0 + DELTA) @ np.linalg.inv(frame(t0))
    axis, point = screw(D)
    if parent is not None:  # the parent's frame at t0 -> the world
        P = transforms(t0)[parent]
        axis, point = P[:3, :3] @ axis, None if point is None else P[:3, :3] @ point + P[:3, 3]
    return axis, point


def carrier(motions: list, k: int) -> int | None:
    """The part (1-based) whose motion is part ``k``'s carrier's in the ground truth (a ``carried``
    record names its parent's motion, not its part): for an exported parent with no Gaussians of its
    own (a frame that only carries)."""
    parent = motions[k].record().get("parent")
    for j, m in enumerate(motions):
        record = m.record()
        if j != k and parent is not None and all(record.get(key) == v for key, v in parent.items()):
            return j + 1
    return None


def rows_of(run: Path) -> list[dict]:
    loaded = load_run(run, "cpu")
    predictor, data = loaded.predictor, Path(loaded.config.data)
    rig, _, xml, report = build_model(loaded)
    gt = _gt(data)
    points, part_ids, transforms, motions = gt
    size = float(np.linalg.norm(points.max(0) - points.min(0)))
    end = 1.0
    motion = simulate(xml, rig, end)
    times = list(np.linspace(predictor.t_max, end, TIMES + 1)[1:])
    mujoco = physics_errors(
        predictor,
        data,
        times,
        positions=lambda t: predictor.gaussians_carried(t, motion.labels, motion.transforms)["means"],
    )["parts"]
    own = physics_errors(predictor, data, times)["parts"]
    _, owner = _parts_at(predictor, predictor.t_max, gt, 0.03)
    labels = motion.labels.to(owner.device)
    body_owner = {}  # exported body -> the ground-truth part most of its Gaussians lie on
    for b in range(1, len(rig.bodies) + 1):
        ids = owner[labels == b]
        ids = ids[ids > 0]
        if len(ids):
            body_owner[b - 1] = int(ids.mode().values)
    rows = []
    for p, m in enumerate(motions, start=1):
        kind = m.record()["type"] if hasattr(m, "record") else "?"
        if kind == "static":
            continue
        sel = labels[owner == p]
        sel = sel[sel > 0]
        row = {"scene": run.name, "part": str(p), "truth": kind, "joint": "none"}
        if len(sel):
            b = int(sel.mode().values) - 1
            body = rig.bodies[b]
            row["joint"] = body.joint + ("" if body.parent is None else " (child)")
            row["joint_right"] = body.joint in expected(kind)
            if body.joint in ("hinge", "slide") and row["joint_right"]:
                parent = None if body.parent is None else body_owner.get(body.parent, carrier(motions, p - 1))
                axis, point = true_joint(transforms, p - 1, None if parent is None else parent - 1, rig.t0)
                row["axis_deg"] = round(math.degrees(math.acos(min(1.0, abs(float(axis @ body.axis))))), 2)
                if point is not None and body.joint == "hinge":
                    off = body.pivot - point
                    off = off - (off @ axis) * axis
                    row["pivot_pct"] = round(100 * float(np.linalg.norm(off)) / size, 2)
        for name, errors in (("mujoco_path_pct", mujoco), ("run_path_pct", own)):
            e = errors.get(str(p), {}).get("mean_trajectory_error")
            row[name] = None if e is None else round(100 * e / size, 2)
        rows.append(row)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("runs", type=Path, nargs="+")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    rows = [r for run in args.runs for r in rows_of(run)]
    for r in rows:
        print("  ".join(f"{k}={r.get(k)}" for k in COLUMNS))
    if args.json is not None:
        command = "benchmarks/simulators.py " + " ".join(str(r) for r in args.runs)
        write_record(args.json, make_record("simulators", rows, command, columns=COLUMNS, notes=NOTES))


if __name__ == "__main__":
    main()
