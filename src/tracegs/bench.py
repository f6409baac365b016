"""Benchmarks beyond the rasteriser: field cost vs FLOPs, and TRACE vs DefGS on synthetic scenes.

Each writes its table into docs/BENCHMARKS.md (``bench_report.update_section``) with the machine,
date and command. Quality numbers come from the held-out splits of scenes generated here; nothing is
tuned or selected on the extrapolation split.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch

from .bench_report import machine_description, markdown_table, update_section
from .config import make_config


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
        body = (
            "## Fields (forward + backward)\n\n"
            f"`tracegs bench fields` on {machine_description()}.\n"
            "GFLOP counts the Linear layers only (forward x 3 for forward + backward).\n\n"
            + markdown_table(records, list(records[0].keys()))
        )
        update_section("fields", body)
    return records


# Paper numbers (extrapolation PSNR / SSIM / LPIPS, Dynamic Multipart mean) shown beside ours.
PAPER_EXTRAPOLATION = {"trace": "33.481 / 0.990 / 0.007", "defgs": "20.664 / - / -"}


def run_train_bench(
    out: Path = Path("runs/bench"),
    scenes: tuple[str, ...] = ("fan",),
    preset: str = "cpu-fast",
    methods: tuple[str, ...] = ("trace", "defgs"),
    resolution: int = 128,
    update_docs: bool = True,
    overrides: dict | None = None,
) -> list[dict]:
    """Synthesise each scene, train every method with the same preset and iterations, evaluate."""
    from .data.synth import synthesize
    from .eval.protocol import evaluate_run
    from .train.trainer import Trainer

    out = Path(out)
    records = []
    for scene in scenes:
        data = out / "scenes" / f"{scene}_{resolution}"
        if not (data / "transforms_test.json").is_file():
            synthesize(scene, data, resolution=resolution, progress=False)
        for method in methods:
            run = out / "runs" / f"{scene}_{method}_{preset}"
            cfg = make_config(preset, data=data, run=run, method=method, **(overrides or {}))
            summary = Trainer(cfg, progress=False).train()
            result = evaluate_run(run, save_images=False)
            (run / "eval.json").write_text(json.dumps(result, indent=2))
            i, e = result["interpolation"], result["extrapolation"]
            records.append(
                {
                    "scene": scene,
                    "method": method,
                    "interp_psnr": i["mae_psnr"],
                    "interp_ssim": i["ssim"],
                    "interp_lpips": i.get("lpips_vgg", float("nan")),
                    "extrap_psnr": e["mae_psnr"],
                    "extrap_ssim": e["ssim"],
                    "extrap_lpips": e.get("lpips_vgg", float("nan")),
                    "train_s": summary["train_seconds"],
                    "iterations": summary["iterations"],
                    "gaussians": summary["gaussians"],
                    "ms_per_it": summary["ms_per_iteration"],
                }
            )
    if update_docs:
        cols = [c for c in records[0] if c != "ms_per_it"]
        timing_rows = [{"scene": r["scene"], "method": r["method"], **r["ms_per_it"]} for r in records]
        body = (
            f"## TRACE vs DefGS on synthetic scenes ({preset}, {resolution} px)\n\n"
            f"`tracegs bench train --scenes {' '.join(scenes)} --preset {preset}` on {machine_description()}.\n"
            "PSNR is MAE-PSNR (the paper's), LPIPS is VGG. Paper, Dynamic Multipart mean, extrapolation "
            f"PSNR / SSIM / LPIPS: TRACE {PAPER_EXTRAPOLATION['trace']}, DefGS {PAPER_EXTRAPOLATION['defgs']}.\n\n"
            + markdown_table(records, cols)
            + "\n\nTime per iteration (ms), averaged over the whole run:\n\n"
            + markdown_table(timing_rows, list(timing_rows[0].keys()))
        )
        update_section(f"train-{preset}", body)
    return records
