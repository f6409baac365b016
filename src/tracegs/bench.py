"""Benchmarks beyond the rasteriser: field cost vs FLOPs, and TRACE vs DefGS on synthetic scenes.

Each writes its table into docs/BENCHMARKS.md (``bench_report.update_section``) with the machine,
date and command. Quality numbers come from the held-out splits of scenes generated here; nothing is
tuned or selected on the extrapolation split.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import torch

from .bench_report import (
    cpu_name,
    load_records,
    machine_description,
    markdown_table,
    merge_records,
    update_section,
)
from .config import make_config
from .utils import atomic_write_text


def _mlp_flops(module: torch.nn.Module, n: int) -> float:
    """Forward multiply-adds x 2 of every Linear layer for ``n`` inputs."""
    return sum(
        2.0 * n * m.in_features * m.out_features for m in module.modules() if isinstance(m, torch.nn.Linear)
    )


def _time(fn, repeats: int = 5) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1000 * sorted(times)[len(times) // 2]


def run_field_bench(n: int = 20_000, update_docs: bool = True) -> list[dict]:
    """Forward+backward time of f_defo and f_trd at the paper's and cpu-fast sizes, fp32 and bf16."""
    from .models.deformation import DeformationField
    from .models.dynamics import DynamicsField

    records = []
    x = torch.rand(n, 3) * 2 - 1
    for preset in ("paper", "cpu-fast"):
        cfg = make_config(preset)
        for name, field in (
            ("f_defo", DeformationField(cfg.deformation)),
            ("f_trd", DynamicsField(cfg.dynamics)),
        ):
            for bf16 in (False, True):

                def run(field=field, bf16=bf16):
                    xx = x.clone().requires_grad_(True)
                    ctx = (
                        torch.autocast("cpu", dtype=torch.bfloat16)
                        if bf16
                        else torch.autocast("cpu", enabled=False)
                    )
                    with ctx:
                        out = field(xx, 0.5)
                    sum(o.float().sum() for o in out if o is not None).backward()

                ms = _time(run)
                gflop = 3 * _mlp_flops(field, n) / 1e9  # backward ~ 2x forward
                records.append(
                    {
                        "cpu": cpu_name(),
                        "preset": preset,
                        "field": name,
                        "dtype": "bf16" if bf16 else "fp32",
                        "gaussians": n,
                        "ms_forward_backward": round(ms, 1),
                        "gflop": round(gflop, 2),
                        "gflop_per_s": round(gflop / (ms / 1000), 1),
                    }
                )
    if update_docs:
        stamp = {"machine": machine_description()}
        table = merge_records("fields", [r | stamp for r in records], ("cpu", "preset", "field", "dtype"))
        machines = "\n".join(f"- {m}" for m in dict.fromkeys(r["machine"] for r in table))
        body = (
            "## Fields (forward + backward)\n\n"
            f"`tracegs bench fields` on (raw records in `docs/results/fields.json`):\n{machines}\n\n"
            "GFLOP counts the Linear layers only (forward x 3 for forward + backward).\n\n"
            + markdown_table(table, [c for c in table[0] if c != "machine"])
        )
        update_section("fields", body)
    return records


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
    "TRACE_4dgs": {"method": "trace", "deformation__kind": "hexplane"},
    "DefGS": {"method": "defgs"},
}

ABLATIONS = {
    "dt=1": {"dynamic__dt_frames": 1.0},
    "dt=2": {},
    "dt=3": {"dynamic__dt_frames": 3.0},
    "order=1": {"dynamics__order": 1},
    "order=3": {"dynamics__order": 3},
    "no f_defo": {"dynamic__use_deformation": False},
    "no physics derivation": {"dynamic__physics_derivation": False},
    "no equivalence": {"dynamics__equivalent": False},
}

# Settings of ours beyond the paper's switches, measured as rows of the ablation tables on request
# (`--variants "skip static"`); not part of a table's default rows.
OPTIONS = {
    "skip static": {"dynamic__skip_static": 0.003},
    "no skip static": {"dynamic__skip_static": 0.0},
    "budget 14k": {"densify__max_gaussians": 14_000},
    "f_defo 4x128": {"deformation__width": 128},
    "hold 2300": {"dynamic__hold_gaussians_steps": 2300},
    "growth 0.4": {"dynamic__time_growth_fraction": 0.4},
    "20k dynamic": {"dynamic_iterations": 20_000},
    "12k dynamic": {"dynamic_iterations": 12_000},
    "24k dynamic": {"dynamic_iterations": 24_000},
    "f_defo time L=3": {"deformation__time_frequencies": 3},
    "growth in 32": {"dynamic__time_growth_stages": 32},
    "growth in 60": {"dynamic__time_growth_stages": 60},
    "f_defo alone 3800": {"dynamic__warmup_deformation_steps": 3800},
    "refine until 8000": {"densify__refine_stop": 8000},
    "budget 14k until 8000": {"densify__max_gaussians": 14_000, "densify__refine_stop": 8000},
    "field lr final 1.6e-5": {"optim__field_lr_final": 1.6e-5},
    "accelerations own MLP": {"dynamics__acceleration_depth": 2},
    "all rates from the own MLP": {
        "dynamics__angular_accelerations_from_head": False,
        "dynamics__detach_acceleration_features": False,
    },
    "accelerations shared head": {
        "dynamics__acceleration_depth": 0,
        "dynamics__detach_acceleration_features": True,
    },
    "angular acceleration penalty": {"dynamic__angular_acceleration_penalty": 0.005},
    "consistency over the step's frames": {"dynamic__consistency_frames": 0.0},
    "consistency on f_defo's particles": {"dynamic__consistency_transport": "deformation"},
}


def _flags(overrides: dict | None) -> str:
    return "".join(f" --{k.replace('_', '-')} {v}" for k, v in (overrides or {}).items())


def scene_folder(out: Path, scene: str, resolution: int, synthesize_missing: bool = True) -> Path | None:
    """A synthetic scene by name (rendered once into ``out/scenes``) or an existing scene folder;
    None if it does not exist yet and ``synthesize_missing`` is off."""
    if Path(scene).is_dir():
        return Path(scene)
    from .data.synth import synthesize

    data = Path(out) / "scenes" / f"{scene}_{resolution}"
    if not (data / "transforms_test.json").is_file():
        if not synthesize_missing:
            return None
        synthesize(scene, data, resolution=resolution, progress=False)
    return data


def _changed_settings(run: Path, cfg) -> list[str] | None:
    """The settings in which ``run`` was made otherwise than ``cfg`` asks (``train.trainer.changed_settings``,
    the question a resume asks; settings added since read as their defaults); None when its config is
    missing or unreadable."""
    from .train.trainer import changed_settings

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


def validation_cut(data: Path, fraction: float, t_end: float | None = None) -> tuple[float, float]:
    """(t_cut, t_end) of a validation future: ``t_end`` is the training span's end (the scene's
    ``t_train_end``, else its last training time) and ``t_cut`` the last training time at or before
    ``fraction`` of it. Training stops at t_cut; the training frames after it are the future scored."""
    from .data.blender import load_scene

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
    update_docs: bool = True,
    train: bool = True,
    command: str | None = None,
    validation: float | None = None,
    methods_table: str = "methods",
) -> list[dict]:
    """Train and evaluate every variant (config overrides) on every scene; one table row each.

    A run folder that already holds ``eval.json`` for the same config is reused, so an interrupted
    benchmark continues where it stopped. ``command`` is the command line recorded with the rows
    (default: the ``tracegs bench`` line that makes them). With ``validation`` (a fraction of the
    training span) every run trains up to that cut and is scored on the training cameras' later
    frames (``validation_cut``): the table for choosing settings, which never sees the test splits.
    A row with TRACE's settings in another table (the ablation "dt=2") is stored as the TRACE record
    of ``methods_table`` and shown from there, so one run is never recorded twice.
    """
    from .config import apply_overrides
    from .eval.protocol import evaluate_run
    from .train.trainer import AFTER_TRAINING, RESUMABLE_CHANGES, Trainer

    records = []
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
            done, changed = run / "eval.json", _changed_settings(run, cfg)
            same = changed == []
            if not (done.is_file() and same) and not train:
                why = "no finished run with these settings"
                if done.is_file() and changed is not None and not set(changed) - AFTER_TRAINING:
                    why = (
                        f"scored with other render-time settings ({', '.join(changed)}); "
                        "run without --report-only to score it again"
                    )
                print(f"{run}: {why}; row skipped")
                continue
            if not (done.is_file() and same):
                if run.exists() and (changed is None or set(changed) - AFTER_TRAINING):
                    _set_aside(run)  # trained with other settings: keep it aside, start afresh
                # else resumed: after the last step only the calibration runs again (a render-time setting)
                summary = Trainer(cfg, progress=False).train()
                result = evaluate_run(run, future_end=future_end)
                atomic_write_text(done, json.dumps(result, indent=2))
            else:
                summary = json.loads((run / "summary.json").read_text())
            result = json.loads(done.read_text())
            i, e = result["interpolation"], result["extrapolation"]
            if validation is None:
                scores = {
                    "interp_psnr": i["mae_psnr"],
                    "interp_ssim": i["ssim"],
                    "interp_lpips": i.get("lpips_vgg", float("nan")),
                    "extrap_psnr": e["mae_psnr"],
                    "extrap_ssim": e["ssim"],
                    "extrap_lpips": e.get("lpips_vgg", float("nan")),
                    "extrap_psnr_new_cams": e.get("per_cameras", {})
                    .get("new_cameras", {})
                    .get("mae_psnr", "-"),
                    "paper_extrap": PAPER.get(label, "-"),
                }
            else:
                scores = {
                    "t_cut": round(result["t_train_end"], 4),
                    "t_end": round(result["future_end"], 4),
                    "val_future_psnr": e["mae_psnr"],
                    "val_future_ssim": e["ssim"],
                    "val_future_lpips": e.get("lpips_vgg", float("nan")),
                    "interp_psnr": i["mae_psnr"],
                }
            records.append(
                {
                    "scene": Path(scene).name,
                    "variant": label,
                    **scores,
                    "train_s": summary["train_seconds"],
                    "iterations": summary["iterations"],
                    "gaussians": summary["gaussians"],
                    "ms_per_it": summary["ms_per_iteration"],
                }
            )
    if update_docs and records:
        cut = "" if validation is None else f" --validation {validation:g}"
        flags = _flags(overrides) + cut
        command = command or f"tracegs bench {name} --scenes {' '.join(scenes)} --preset {preset}{flags}"
        stamp = {"command": command, "machine": machine_description()}
        # settings a run may be resumed with (the device, ...) leave it the same run and the same table:
        # they are in each row's command, not in the table's name
        same_table = {
            k: v for k, v in (overrides or {}).items() if k.replace("__", ".") not in RESUMABLE_CHANGES
        }
        suffix = f"-{preset}{(_flags(same_table) + cut).replace(' ', '')}"
        stored = [r | stamp for r in records]
        # A row with TRACE's settings (the ablation "dt=2") is the methods table's TRACE run: it is
        # stored once, as that table's TRACE record, and shown here from there. Validation tables have
        # no methods counterpart and keep their own rows.
        shares = validation is None and name != methods_table
        shared = {label for label, v in variants.items() if _same_as_trace(v)} if shares else set()
        as_trace = [
            r | {"variant": "TRACE", "paper_extrap": PAPER["TRACE"]} for r in stored if r["variant"] in shared
        ]
        if as_trace:
            table = merge_records(methods_table + suffix, as_trace, ("scene", "variant"))
            update_section(
                methods_table + suffix, variant_table_markdown(methods_table, preset, resolution, table)
            )
        table = merge_records(
            name + suffix, [r for r in stored if r["variant"] not in shared], ("scene", "variant")
        )
        if shares:
            scenes_shown = {r["scene"] for r in table + records}
            table = table + _trace_rows(methods_table + suffix, scenes_shown, methods_table)
        title = name if validation is None else f"{name}, validation future"
        update_section(name + suffix, variant_table_markdown(title, preset, resolution, table))
    return records


def _same_as_trace(variant: dict) -> bool:
    return not variant or variant == METHODS["TRACE"]


def _trace_rows(section: str, scenes: set[str], methods_table: str) -> list[dict]:
    """The TRACE records of the methods table ``section`` for ``scenes``, labelled as the ablation
    with TRACE's settings: that ablation's rows, shown in its table but stored once."""
    label = next(k for k, v in ABLATIONS.items() if _same_as_trace(v))
    rows = load_records(section)
    shown = f"the {methods_table} table's TRACE row, the same run"
    return [
        r
        | {
            "variant": label,
            "paper_extrap": PAPER[label],
            "note": "; ".join(filter(None, [shown, r.get("note")])),
        }
        for r in rows
        if r.get("variant") == "TRACE" and r.get("scene") in scenes
    ]


def variant_table_markdown(name: str, preset: str, resolution: int, records: list[dict]) -> str:
    """The quality table and the per-iteration timing table of ``records`` (each with its command and
    machine), as a section of docs/BENCHMARKS.md. Rows are shown scene by scene (in the order the
    scenes were first measured), each scene's rows in the order of METHODS and ABLATIONS, so a row
    added later still sits beside the rows it is compared with."""
    scene_rank = {s: i for i, s in enumerate(dict.fromkeys(r["scene"] for r in records))}
    variant_rank = {v: i for i, v in enumerate({**METHODS, **ABLATIONS, **OPTIONS})}
    records = sorted(
        records, key=lambda r: (scene_rank[r["scene"]], variant_rank.get(r["variant"], len(variant_rank)))
    )
    hidden = ("ms_per_it", "command", "machine", "note")
    cols = [c for c in dict.fromkeys(k for r in records for k in r) if c not in hidden]
    timing_rows = [{"scene": r["scene"], "variant": r["variant"], **r["ms_per_it"]} for r in records]
    groups: dict[tuple, list[str]] = {}
    for r in records:
        groups.setdefault((r["command"], r["machine"], r.get("note")), []).append(
            f"{r['scene']} {r['variant']}"
        )
    provenance = "\n".join(
        f"- {', '.join(rows)}: `{c}` on {m}" + (f" ({n})" if n else "") for (c, m, n), rows in groups.items()
    )
    if "val_future_psnr" in records[0]:
        legend = (
            "Validation future, for choosing settings without the test splits: each run trains on "
            "t <= `t_cut` and is scored on the training cameras' frames at `t_cut` < t <= `t_end` (the rest "
            "of the training span); `interp_psnr` is the held-out cameras at t <= `t_cut`. PSNR is "
            "MAE-PSNR, LPIPS is VGG.\n\n"
        )
    else:
        legend = (
            "PSNR is MAE-PSNR (the paper's), LPIPS is VGG; `extrap_psnr_new_cams` is the extrapolation "
            "PSNR of the held-out cameras alone (future time and a new view); `paper_extrap` is the "
            "paper's extrapolation PSNR / SSIM / LPIPS for the corresponding row (Dynamic Multipart mean; "
            "its scenes differ from ours).\n\n"
        )
    return (
        f"## {name} ({preset}, {resolution} px)\n\n"
        f"Rows measured by (raw records in `docs/results/`):\n{provenance}\n\n"
        + legend
        + markdown_table(records, cols)
        + "\n\nTime per training iteration (ms), averaged over the whole run:\n\n"
        + markdown_table(timing_rows, list(timing_rows[0].keys()))
    )
