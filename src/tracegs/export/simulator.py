"""``tracegs export --mjcf FILE --urdf DIR``: a trained run's parts, joints and identified models as a
MuJoCo model and a URDF (``rig.py``, ``mjcf.py``, ``urdf.py``), checked on the way out: MuJoCo loads the
MJCF and runs it from the handover over the future, and each body's Gaussians moved by it are compared
with where the run's own extrapolation puts them (the report's ``check``); yourdfpy loads the URDF
with its meshes.

The parts are the run's calibrated ones (its extrapolation state), so no segmentation is needed; a run
calibrated by an older version is told to run ``tracegs calibrate`` first.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ..data.cameras import scene_extent_from_cameras
from ..data.scene import load_scene
from ..run import RunError, load_run
from ..utils import atomic_write_text
from .mjcf import mjcf_text, rig_hulls
from .rig import find_rig
from .simulate import load_urdf, simulate

CHECK_TIMES = 12
"""Times over the future at which the simulated Gaussians are compared with the run's."""


def scene_frame(data: Path, downscale: int, t_max: float) -> tuple[float, np.ndarray]:
    """``(extent, up [3])`` of the scene's training cameras: 3DGS's extent of their centres, and their
    mean up (OpenCV's -y of each camera, in the world)."""
    frames = [f for f in load_scene(data, "train", downscale).frames if f.time <= t_max + 1e-9]
    cameras = {id(f.camera.viewmat): f.camera for f in frames}.values()
    centres = torch.stack([c.center.cpu() for c in cameras])
    up = -torch.stack([c.viewmat[1, :3].cpu() for c in cameras]).double().mean(0)
    return scene_extent_from_cameras(centres), (up / up.norm()).numpy()


def path_errors(predictor, rig, motion, times: list[float], extent: float) -> list[dict]:
    """Per body: the mean distance over ``times`` between its Gaussians moved by ``motion``
    (``SimulatedMotion``) and the run's own prediction, in fractions of ``extent``."""
    distances = {body.name: [] for body in rig.bodies}
    for t in times:
        own = predictor.gaussians_at(t)["means"]
        simulated = predictor.gaussians_carried(t, motion.labels, motion.transforms)["means"]
        for body in rig.bodies:
            rows = body.rows.to(own.device)
            if bool(rows.any()):
                distances[body.name].append(float((own[rows] - simulated[rows]).norm(dim=-1).mean()))
    return [
        {"body": name, "mean_path_error": float(np.mean(d)) / extent if d else None}
        for name, d in distances.items()
    ]


def build_model(loaded, data: Path | None = None) -> tuple:
    """``(rig, hulls, MJCF text, report)`` of the loaded run ``loaded`` (``run.load_run``), the scene's
    extent and up from the training cameras of ``data`` (default: the run's scene)."""
    predictor, cfg = loaded.predictor, loaded.config
    if predictor.model.dynamics is None:
        raise RunError(
            f"{loaded.path}: a {predictor.model.method} run has no physics to export (train TRACE)"
        )
    extent, up = scene_frame(Path(data or cfg.data), cfg.downscale, predictor.t_max)
    rig = find_rig(predictor, extent, up)
    hulls = rig_hulls(rig)
    xml, report = mjcf_text(rig, hulls)
    facts = {
        "run": str(loaded.path),
        "extent": extent,
        "up": up.tolist(),
        "parts_from": "the run's calibration",
    }
    return rig, hulls, xml, facts | report


def simulated_motion(loaded, t_end: float, data: Path | None = None):
    """The run's MuJoCo model (``build_model``, its scene ``data``) run from the handover to ``t_end``
    (``SimulatedMotion``): the viewer's third motion."""
    rig, _, xml, _ = build_model(loaded, data)
    return simulate(xml, rig, t_end)


def export_simulator(
    run: str | Path,
    mjcf: str | Path | None = None,
    urdf: str | Path | None = None,
    device: str = "auto",
    t_end: float = 1.0,
) -> dict:
    """Write the MJCF ``mjcf`` and/or the URDF folder ``urdf`` of ``run`` (module docstring) and return
    the report: per body its joint, model, terms and what has no simulator term, and the check of the
    MuJoCo rollout against the run's own extrapolation up to ``t_end``."""
    if mjcf is None and urdf is None:
        raise ValueError("give --mjcf FILE and/or --urdf DIR")
    run = Path(run)
    loaded = load_run(run, device)
    predictor = loaded.predictor
    rig, hulls, xml, report = build_model(loaded)
    if mjcf is not None:
        report["mjcf"] = str(atomic_write_text(Path(mjcf), xml + "\n"))
    if urdf is not None:
        from .urdf import write_urdf

        path, report["urdf"] = write_urdf(rig, hulls, Path(urdf), run.name or "tracegs")
        load_urdf(path)
    end = max(t_end, predictor.t_max)
    motion = simulate(xml, rig, end)
    times = list(np.linspace(predictor.t_max, end, CHECK_TIMES + 1)[1:]) if end > predictor.t_max else []
    report["check"] = {
        "simulator": "MuJoCo",
        "finite": motion.finite,
        "times": [float(t) for t in times],
        "against_the_run": path_errors(predictor, rig, motion, times, report["extent"]),
        "units": "fractions of the scene extent",
    }
    return report


def format_report(report: dict) -> str:
    """The console lines of ``export_simulator``'s report."""
    lines = [f"gravity {np.round(report['gravity'], 4).tolist()} ({report['gravity_from']})"]
    errors = {e["body"]: e["mean_path_error"] for e in report["check"]["against_the_run"]}
    for body in report["bodies"]:
        error = errors.get(body["body"])
        lines.append(
            f"{body['body']}: {body['joint']}"
            + (f" on {body['parent']}" if body.get("parent") else "")
            + f" - {body['why']}"
            + (f"; MuJoCo vs the run: {100 * error:.2f}% of the scene" if error is not None else "")
            + (f"; left out: {', '.join(body['left_out'])}" if body["left_out"] else "")
        )
    lines += [
        f"wrote {report[k] if isinstance(report[k], str) else report[k]['file']}"
        for k in ("mjcf", "urdf")
        if k in report
    ]
    return "\n".join(lines)
