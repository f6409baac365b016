"""Quality benchmarks: TRACE, TRACE_4dgs, DefGS and Hold (``methods``) and the paper's Table 4 switches
(``ablations``) trained and scored on synthetic scenes or scene folders, one row per (scene, variant).

Quality comes from the held-out splits (or, with ``validation``, a future cut from the training span
for choosing settings); nothing is tuned or selected on the extrapolation split.
"""

from __future__ import annotations

from pathlib import Path

from ..config import make_config
from ..results import make_record, write_record
from ..run import is_after_training
from .sweep import Cell, run_cells

# Paper numbers (extrapolation PSNR / SSIM / LPIPS) shown beside ours: Dynamic Multipart mean
# (Table 1 / appendix) for the methods, and Table 4 (Multipart) for the ablations.
PAPER = {
    "TRACE": "33.481 / 0.990 / 0.007",
    "TRACE_4dgs": "32.317 / 0.985 / 0.016",
    "DefGS": "20.664 / 0.931 / 0.067",
    "dt=1": "32.852 / 0.989 / 0.010",
    "dt=2": "33.481 / 0.990 / 0.007",
    "dt=3": "33.003 / 0.989 / 0.008",
    "order=1": "33.125 / 0.989 / 0.010",
    "order=3": "33.312 / 0.989 / 0.008",
    "no f_defo": "19.206 / 0.907 / 0.120",
    "no physics derivation": "29.602 / 0.983 / 0.012",
    "no equivalence": "29.986 / 0.985 / 0.012",
}

METHODS = {
    "TRACE": {"method": "trace"},
    "TRACE_4dgs": {"method": "trace", "deformation.kind": "hexplane"},
    "DefGS": {"method": "defgs"},
    "Hold": {"method": "trace"},
    "TRACE joint laws": {"method": "trace", "extrapolation.joint_laws": True},
    "TRACE paper extrapolation": {"method": "trace", "extrapolation.joint_laws": False},
}

MOTIONS = {"Hold": "hold"}
"""Rows that score another row's trained run with another motion (``Predictor.gaussians_at``) and
train nothing: Hold is the TRACE row's run (its folder: its settings are TRACE's) with f_defo up to
the training span's end and its Gaussians there held still after it (the baseline a prediction must
beat), scored into ``RUN/eval_hold.json``; without a finished TRACE run the row is skipped."""

ABLATIONS = {
    "dt=1": {"stage2.dt_frames": 1.0},
    "dt=2": {},
    "dt=3": {"stage2.dt_frames": 3.0},
    "order=1": {"dynamics.order": 1},
    "order=3": {"dynamics.order": 3},
    "no f_defo": {"stage2.use_deformation": False},
    "no physics derivation": {"stage2.physics_derivation": False},
    "no equivalence": {"dynamics.equivalent": False},
}

# Settings of ours beyond the paper's switches, measured as rows of the ablation tables on request
# (`--variants "skip static"`); not part of a table's default rows.
OPTIONS = {
    "skip static": {"stage2.skip_static": True},
    "no skip static": {"stage2.skip_static": False},
    "budget 14k": {"densify.max_gaussians": 14_000},
    "f_defo 4x128": {"deformation.width": 128},
    "growth 0.4": {"stage2.time_growth_fraction": 0.4},
    "20k dynamic": {"dynamic_iterations": 20_000},
    "12k dynamic": {"dynamic_iterations": 12_000},
    "24k dynamic": {"dynamic_iterations": 24_000},
    "f_defo time L=3": {"deformation.time_frequencies": 3},
    "growth in 32": {"stage2.time_growth_stages": 32},
    "growth in 60": {"stage2.time_growth_stages": 60},
    "refine until 8000": {"densify.refine_stop": 8000},
    "budget 14k until 8000": {"densify.max_gaussians": 14_000, "densify.refine_stop": 8000},
    "field lr final 1.6e-5": {"optim.field_lr_final": 1.6e-5},
    "accelerations own MLP": {"dynamics.acceleration_depth": 2},
    "all rates from the own MLP": {
        "dynamics.angular_accelerations_from_head": False,
        "dynamics.detach_acceleration_features": False,
    },
    "accelerations shared head": {
        "dynamics.acceleration_depth": 0,
        "dynamics.detach_acceleration_features": True,
    },
    "consistency over the step's frames": {"stage2.consistency_frames": 0.0},
    "painters held": {"extrapolation.surface_painters": "hold"},
    "painters stopped at the edge": {"extrapolation.surface_painters": "edge"},
    "2 views 8k dynamic": {"stage2.views_per_step": 2, "dynamic_iterations": 8_000},
    "3 views 6k dynamic": {"stage2.views_per_step": 3, "dynamic_iterations": 6_000},
    "4 views 5k dynamic": {"stage2.views_per_step": 4, "dynamic_iterations": 5_000},
    "half steps": {"dynamic_iterations": 10_000, "densify.refine_stop": 3000},
    "half steps, field lr x2": {
        "dynamic_iterations": 10_000,
        "densify.refine_stop": 3000,
        "optim.field_lr": 1.6e-3,
    },
}


def _flags(overrides: dict | None) -> str:
    """Settings by dotted name as the command line spells them: ``--stage2.dt-frames 1.0``."""
    return "".join(f" --{k.replace('_', '-')} {v}" for k, v in (overrides or {}).items())


def scene_folder(out: Path, scene: str, resolution: int, synthesize_missing: bool = True) -> Path | None:
    """A synthetic scene by name (rendered once into ``out/scenes``) or an existing scene folder;
    None if it does not exist yet and ``synthesize_missing`` is off."""
    if Path(scene).is_dir():
        return Path(scene)
    from ..data.synth import synthesize

    data = Path(out) / "scenes" / f"{scene}_{resolution}"
    if not (data / "transforms_test.json").is_file():
        if not synthesize_missing:
            return None
        synthesize(scene, data, resolution=resolution, progress=False)
    return data


def validation_cut(data: Path, fraction: float, t_end: float | None = None) -> tuple[float, float]:
    """(t_cut, t_end) of a validation future: ``t_end`` is the training span's end (the scene's
    ``t_train_end``, else its last training time) and ``t_cut`` the last training time at or before
    ``fraction`` of it. Training stops at t_cut; the training frames after it are the future scored."""
    from ..data.scene import load_scene

    if not 0.0 < fraction < 1.0:
        raise ValueError(f"validation fraction {fraction}: must lie strictly between 0 and 1")
    train = load_scene(data, "train")  # frame times only: the image size does not matter
    times = sorted({f.time for f in train.frames})
    if t_end is None:
        t_end = train.t_train_end if train.t_train_end is not None else times[-1]
    before = [t for t in times if t <= fraction * t_end + 1e-9]
    if len(before) < 2 or not any(before[-1] < t <= t_end + 1e-9 for t in times):
        raise ValueError(
            f"{data}: too few training times to cut a validation future at {fraction} x {t_end:g}"
        )
    return before[-1], t_end


def run_variant_table(
    name: str,
    variants: dict[str, dict],
    out: Path = Path("runs/bench"),
    scenes: tuple[str, ...] = ("fan",),
    preset: str = "cpu-fast",
    resolution: int = 128,
    overrides: dict | None = None,
    train: bool = True,
    command: str | None = None,
    validation: float | None = None,
    json_path: str | Path | None = None,
    cluster: str | None = None,
    cpus_per_task: int = 1,
) -> list[dict]:
    """Train and evaluate every variant (config overrides) on every scene; one table row each.

    A run folder that already holds ``eval.json`` for the same config is reused, so an interrupted
    benchmark continues where it stopped. ``command`` is the command line recorded with the rows
    (default: the ``tracegs bench`` line that makes them). With ``validation`` (a fraction of the
    training span) every run trains up to that cut and is scored on the training cameras' later
    frames (``validation_cut``): the table for choosing settings, which never sees the test splits.
    Rows with the same settings share one run folder (the ablation "dt=2" is the TRACE row, and Hold
    is the TRACE row's run scored with another motion, ``MOTIONS``). With
    ``json_path`` the rows are written there as a results record (``tracegs.results``).

    The rows train one after the other in this process; with ``cluster`` (``"auto"``: a local Ray on
    every CPU, else a Ray address) each row is a Ray task of ``cpus_per_task`` CPUs (``bench.sweep``),
    with the same rows, run folders and record.
    """
    from ..config import apply_overrides

    cells = []
    for scene in scenes:
        data = scene_folder(out, scene, resolution, synthesize_missing=train)
        if data is None:
            continue
        scene_overrides, future_end, suffix = dict(overrides or {}), None, ""
        if validation is not None:
            t_cut, future_end = validation_cut(data, validation, scene_overrides.get("t_train_end"))
            scene_overrides["t_train_end"], suffix = t_cut, f"_val{validation:g}"
        for label, variant in variants.items():
            # rows with the same settings share one run folder (the ablation "dt=2" is the TRACE row)
            slug = "TRACE" if _same_as_trace(variant) else label.replace(" ", "_").replace("=", "")
            run = Path(out) / "runs" / f"{Path(scene).name}_{slug}_{preset}{suffix}"
            cfg = apply_overrides(make_config(preset, data=data, run=run), {**scene_overrides, **variant})
            cells.append(
                Cell(
                    Path(scene).name,
                    label,
                    run,
                    cfg,
                    trace_run=run.with_name(f"{Path(scene).name}_TRACE_{preset}{suffix}"),
                    after_training_only=_after_training_only(variant),
                    paper=PAPER.get(label, "-"),
                    future_end=future_end,
                    validation=validation is not None,
                    train=train,
                    motion=MOTIONS.get(label, "trace"),
                )
            )
    records = run_cells(cells, cluster, cpus_per_task)
    if json_path is not None and records:
        cut = "" if validation is None else f" --validation {validation:g}"
        command = (
            command
            or f"tracegs bench {name} --scenes {' '.join(scenes)} --preset {preset}{_flags(overrides)}{cut}"
        )
        title = f"{name} ({preset}, {resolution} px)" + ("" if validation is None else ", validation future")
        write_record(
            json_path, make_record(name, _flat(records), command, title=title, columns=_columns(records))
        )
    return records


def _after_training_only(variant: dict) -> bool:
    """Whether ``variant`` differs from TRACE only in settings read after the last step."""
    extra = {k: v for k, v in variant.items() if METHODS["TRACE"].get(k) != v}
    return bool(extra) and variant.get("method", "trace") == "trace" and all(map(is_after_training, extra))


def _same_as_trace(variant: dict) -> bool:
    return not variant or variant == METHODS["TRACE"]


def _columns(records: list[dict]) -> list[str]:
    """The columns of a variant table: every score, not the per-part timings."""
    return [c for c in dict.fromkeys(k for r in records for k in r) if c != "ms_per_it"]


def _flat(records: list[dict]) -> list[dict]:
    """The rows as a results record holds them: the per-part timings as columns of their own."""
    return [
        {k: v for k, v in r.items() if k != "ms_per_it"}
        | {f"ms_{k}": v for k, v in r.get("ms_per_it", {}).items()}
        for r in records
    ]
