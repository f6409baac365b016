"""Cost of the fields: forward + backward of f_defo and f_trd at the paper's and cpu-fast's sizes, in
fp32 and bf16, against their FLOPs (``tracegs bench fields``)."""

from __future__ import annotations

import time
from pathlib import Path

import torch

from ..config import make_config
from ..results import make_record, write_record


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


def run_field_bench(n: int = 20_000, json_path: str | Path | None = None) -> list[dict]:
    """Forward+backward time of f_defo and f_trd at the paper's and cpu-fast sizes, fp32 and bf16."""
    from ..models.deformation import DeformationField
    from ..models.dynamics import DynamicsField

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
    if json_path is not None:
        command = f"tracegs bench fields --json {json_path}"
        title = "f_defo and f_trd forward + backward on 20k points (GFLOP: the Linear layers, x 3)"
        write_record(json_path, make_record("fields", records, command, title=title))
    return records
