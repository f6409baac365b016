"""The cells of a variant table, one (scene, variant) each, run in order in this process or as Ray
tasks (``cluster``): each cell trains its run folder if needed, scores it and gives its table row.

A row that differs from TRACE only after training copies the scene's TRACE training
(``Cell.after_training_only``), so it runs once that cell has finished; a second row with the same
run folder waits for the first (``dependencies``), as the Hold row does: it scores the TRACE run with
another motion (``Cell.motion``) and trains nothing of its own. In order, such a row runs right after
the cell it waits for; on Ray it is a task that receives that cell's result. Ray is imported only on
the Ray path (``pip install -e ".[cluster]"``).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ..run import CHECKPOINT, CONFIG, LOG, SUMMARY, changed_settings, training_changes
from ..utils import atomic_write_text

RAY_MISSING = 'ray is not installed: pip install -e ".[cluster]"'
OBJECT_STORE_BYTES = 100 * 1024**2
"""The local Ray's object store: the tasks pass only rows, and the run folders are files."""


class RayMissing(ImportError, ValueError):
    """Ray was asked for and is not installed (a ValueError, so the CLI prints it as one line)."""


@dataclass
class Cell:
    """One row of a table: the run folder ``run`` trained with ``cfg`` and scored."""

    scene: str
    label: str
    run: Path
    cfg: Any
    trace_run: Path
    """The scene's TRACE run folder, whose training an after-training-only row copies."""
    after_training_only: bool = False
    paper: str = "-"
    """The paper's numbers shown beside the row."""
    future_end: float | None = None
    """With a validation cut: the end of the scored future (``validation_cut``)."""
    validation: bool = False
    train: bool = True
    """False: report only (a row without a finished run with these settings is skipped)."""
    motion: str = "trace"
    """How the run's Gaussians move when it is scored (``Predictor.gaussians_at``); another motion
    than ``trace`` scores the run of ``run`` into ``RUN/eval_<motion>.json``."""


def dependencies(cells: list[Cell]) -> dict[int, int]:
    """Cell index -> the index of the cell that must finish first: an after-training-only row waits
    for its scene's TRACE cell (when that is part of the sweep), a row for the first one with its run
    folder that trains it (scores it with the motion ``trace``; a row of another motion trains nothing)."""
    first: dict[Path, int] = {}
    for i, cell in enumerate(cells):
        if cell.motion == "trace":
            first.setdefault(cell.run, i)
    for i, cell in enumerate(cells):
        first.setdefault(cell.run, i)
    waits = {}
    for i, cell in enumerate(cells):
        if first[cell.run] != i:
            waits[i] = first[cell.run]
        elif cell.after_training_only and cell.trace_run in first:
            waits[i] = first[cell.trace_run]
    return waits


def schedule(cells: list[Cell]) -> list[int]:
    """The order in which the cells run: the table's order, except that a cell waiting for a later
    one runs right after it (for a table that lists TRACE first, the table's order)."""
    waits, order, held = dependencies(cells), [], {}

    def place(i: int) -> None:
        order.append(i)
        for j in held.pop(i, []):
            place(j)

    for i in range(len(cells)):
        if i in waits and waits[i] not in order:
            held.setdefault(waits[i], []).append(i)
        else:
            place(i)
    return order


def run_cells(cells: list[Cell], cluster: str | None = None, cpus_per_task: int = 1) -> list[dict]:
    """The rows of ``cells`` in their order (cells without a row left out): run here one after the
    other (``cluster`` None), or as Ray tasks of ``cpus_per_task`` CPUs each on a local Ray
    (``cluster="auto"``) or the cluster at the address ``cluster``."""
    if cluster is None:
        rows = {i: run_cell(cells[i]) for i in schedule(cells)}
    else:
        rows = _run_on_ray(cells, cluster, cpus_per_task)
    return [rows[i] for i in range(len(cells)) if rows[i] is not None]


def run_cell(cell: Cell) -> dict | None:
    """Train ``cell``'s run if it has no finished run with its settings, score it, and give its row;
    None when report-only, or a row of another motion than ``trace``, finds nothing to report."""
    from ..eval.protocol import evaluate_run
    from ..train.trainer import Trainer

    run, cfg = cell.run, cell.cfg
    done, changed = run / "eval.json", _changed_settings(run, cfg)
    same = changed == []
    if not (done.is_file() and same) and (not cell.train or cell.motion != "trace"):
        why = "no finished run with these settings"
        if cell.motion != "trace":  # Hold trains nothing: its run is the TRACE row's
            why += f" to score with the motion {cell.motion!r} (the TRACE row makes it)"
        elif done.is_file() and changed is not None and not training_changes(changed):
            why = (
                f"scored with other render-time settings ({', '.join(changed)}); "
                "run without --report-only to score it again"
            )
        print(f"{run}: {why}; row skipped")
        return None
    if not (done.is_file() and same):
        if not run.exists() and cell.after_training_only:
            _copy_training(cell.trace_run, run)  # calibrated and scored anew, not trained again
            changed = _changed_settings(run, cfg)
        if run.exists() and (changed is None or training_changes(changed)):
            _set_aside(run)  # trained with other settings: keep it aside, start afresh
        # else resumed: after the last step only the calibration runs again (a render-time setting)
        summary = Trainer(cfg, progress=False).train()
        result = evaluate_run(run, future_end=cell.future_end)
        atomic_write_text(done, json.dumps(result, indent=2))
    else:
        summary = json.loads((run / "summary.json").read_text())
    result = json.loads(done.read_text()) if cell.motion == "trace" else _scored_with_motion(cell, done)
    if result is None:
        return None
    return {
        "scene": cell.scene,
        "variant": cell.label,
        **_scores(result, cell),
        "train_s": summary["train_seconds"],
        "iterations": summary["iterations"],
        "gaussians": summary["gaussians"],
        "ms_per_it": summary["ms_per_iteration"],
    }


def _scored_with_motion(cell: Cell, done: Path) -> dict | None:
    """``cell.run`` scored with ``cell.motion``, kept in ``RUN/eval_<motion>.json`` while that file is
    not older than the run's own ``eval.json`` (``done``: the same training and settings); report-only
    (``cell.train`` off) scores nothing and gives None when it is missing."""
    from ..eval.protocol import evaluate_run

    path = cell.run / f"eval_{cell.motion}.json"
    if not (path.is_file() and path.stat().st_mtime >= done.stat().st_mtime):
        if not cell.train:
            print(f"{cell.run}: not scored with the motion {cell.motion!r} yet; row skipped")
            return None
        out = cell.run / f"eval_{cell.motion}"
        result = evaluate_run(cell.run, future_end=cell.future_end, out=out, motion=cell.motion)
        atomic_write_text(path, json.dumps(result, indent=2))
    return json.loads(path.read_text())


def _scores(result: dict, cell: Cell) -> dict:
    i, e = result["interpolation"], result["extrapolation"]
    if not cell.validation:
        return {
            "interp_psnr": i["mae_psnr"],
            "interp_ssim": i["ssim"],
            "interp_lpips": i.get("lpips_vgg", float("nan")),
            "extrap_psnr": e["mae_psnr"],
            "extrap_ssim": e["ssim"],
            "extrap_lpips": e.get("lpips_vgg", float("nan")),
            "extrap_psnr_new_cams": e.get("per_cameras", {}).get("new_cameras", {}).get("mae_psnr", "-"),
            "extrap_moving_psnr": e.get("moving", {}).get("mae_psnr", "-"),
            "paper_extrap": cell.paper,
        }
    return {
        "t_cut": round(result["t_train_end"], 4),
        "t_end": round(result["future_end"], 4),
        "val_future_psnr": e["mae_psnr"],
        "val_future_ssim": e["ssim"],
        "val_future_lpips": e.get("lpips_vgg", float("nan")),
        "interp_psnr": i["mae_psnr"],
    }


def _changed_settings(run: Path, cfg) -> list[str] | None:
    """The settings in which ``run`` was made otherwise than ``cfg`` asks (``run.changed_settings``,
    the question a resume asks; settings added since read as their defaults); None when its config is
    missing or unreadable."""
    try:
        return changed_settings(json.loads((run / "config.json").read_text()), cfg)
    except (FileNotFoundError, ValueError):
        return None


def _set_aside(run: Path) -> None:
    """Rename a benchmark run folder made with other settings to ``RUN.previous`` (one kept)."""
    previous = run.with_name(run.name + ".previous")
    if previous.exists():
        shutil.rmtree(previous)
    run.rename(previous)
    print(f"{run}: made with other settings; moved to {previous} and retraining")


def _copy_training(trace_run: Path, run: Path) -> None:
    """The training of the finished TRACE run ``trace_run`` copied into ``run`` (a row that differs
    only after training then resumes it: its steps are done, so it is only calibrated and scored)."""
    if not (trace_run / SUMMARY).is_file():
        return
    run.mkdir(parents=True)
    for name in (CHECKPOINT, CONFIG, LOG):
        shutil.copy2(trace_run / name, run / name)
    print(f"{run}: the training of {trace_run}, calibrated and scored with its own settings")


# ----- Ray ------------------------------------------------------------------------------------------
def _import_ray():
    try:
        import ray
    except ImportError:
        raise RayMissing(RAY_MISSING) from None
    return ray


def _run_on_ray(cells: list[Cell], cluster: str, cpus_per_task: int) -> dict[int, dict | None]:
    """Every cell a Ray task of ``cpus_per_task`` CPUs (torch and OpenMP threads set to match); a
    cell that waits for another receives that one's result as an argument, so Ray starts it after.
    The tasks' printed lines are printed here as each task finishes."""
    if cpus_per_task < 1:
        raise ValueError(f"--cpus-per-task {cpus_per_task}: must be at least 1")
    if cluster == "auto" and cpus_per_task > (os.cpu_count() or 1):
        raise ValueError(f"--cpus-per-task {cpus_per_task}: this machine has {os.cpu_count()} CPUs")
    ray = _import_ray()
    started = not ray.is_initialized()
    if started and cluster == "auto":
        ray.init(
            address="local",  # a new local Ray, even where one runs already
            num_cpus=os.cpu_count(),
            include_dashboard=False,
            object_store_memory=OBJECT_STORE_BYTES,
            log_to_driver=False,
        )
    elif started:
        ray.init(address=cluster, log_to_driver=False)
    try:
        threads = str(cpus_per_task)
        task = ray.remote(
            num_cpus=cpus_per_task,
            max_retries=0,  # a failed training is reported, not started again
            runtime_env={"env_vars": {"OMP_NUM_THREADS": threads, "MKL_NUM_THREADS": threads}},
        )(_ray_task)
        waits, refs = dependencies(cells), {}
        for i in schedule(cells):  # a cell's dependency is submitted before it
            refs[i] = task.remote(cells[i], os.getcwd(), cpus_per_task, refs.get(waits.get(i)))
        index = {ref: i for i, ref in refs.items()}
        rows, pending = {}, list(refs.values())
        while pending:
            (ready,), pending = ray.wait(pending, num_returns=1)
            rows[index[ready]], printed = ray.get(ready)
            print(printed, end="")
        return rows
    finally:
        if started:
            ray.shutdown()


def _ray_task(cell: Cell, cwd: str, threads: int, after: Any = None) -> tuple[dict | None, str]:
    """One cell in a Ray worker, in the driver's working folder (relative run folders then name the
    same files), on ``threads`` torch threads; ``after`` (the row of the cell it waits for) is only
    there to order it. Gives the row and the lines it printed."""
    import torch

    del after
    torch.set_num_threads(threads)
    os.chdir(cwd)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        row = run_cell(cell)
    return row, printed.getvalue()
