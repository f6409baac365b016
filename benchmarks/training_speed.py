"""Where a training step's time goes, on this CPU: the SSIM of the loss (pytorch-msssim against the
native kernel), the step's parts with 1-4 views per step, the fields in bf16 against float32 (where the
CPU has bf16 in hardware), and a step beside a busy core with two threads against the thread count
`train/threads.py` chooses.

The step timings run the steps of a trained run (its checkpoint, late in stage 2, where the demo spends
most of its time) on a copy of the run folder; nothing of the run is changed. Run it alone on the
machine (other work on the cores is what the busy-core rows add on purpose).
Usage: .venv/bin/python benchmarks/training_speed.py --run runs/demo/trace [--json docs/results/training-speed.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

from tracegs.config import TrainConfig, apply_overrides, config_from_dict
from tracegs.image_metrics import ssim
from tracegs.machine import this_machine
from tracegs.render.ssim import training_ssim
from tracegs.results import make_record, write_record
from tracegs.train.threads import ThreadPolicy
from tracegs.train.trainer import Trainer

DTYPE_ROWS = "training step, the fields' dtype"
"""The ``what`` of the rows that time the fields in bf16 against float32."""


def ssim_ms(fn, size: int, threads: int, repeats: int = 300) -> float:
    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    target = torch.rand(size, size, 3, generator=g)
    image = (target + 0.05 * torch.randn(size, size, 3, generator=g)).clamp(0, 1).requires_grad_()
    for _ in range(20):
        fn(image, target).backward()
    start = time.perf_counter()
    for _ in range(repeats):
        fn(image, target).backward()
    return 1000 * (time.perf_counter() - start) / repeats


def trainer_at(run: Path, work: Path, step_fraction: float, data: Path | None = None, **settings) -> Trainer:
    """A trainer resumed from ``run``'s checkpoint in a copy of the folder, at that fraction of its steps."""
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    for name in ("checkpoint.pt", "config.json"):
        shutil.copy(run / name, work / name)
    cfg = config_from_dict(TrainConfig, json.loads((run / "config.json").read_text()))
    cfg = apply_overrides(cfg, {"run": work, "threads": 0} | ({"data": data} if data else {}))
    trainer = Trainer(cfg, progress=False)
    for key, value in settings.items():  # read per step: changed after the resume's settings check
        section, _, name = key.rpartition(".")
        setattr(getattr(trainer.cfg, section) if section else trainer.cfg, name, value)
    # (the scene has that many cameras a time)
    trainer.sampler.views_per_step = trainer.cfg.stage2.views_per_step
    trainer.state.step = int(step_fraction * trainer.total_steps)
    return trainer


def time_steps(trainer: Trainer, steps: int, threads: ThreadPolicy | None = None) -> dict:
    for _ in range(10):
        trainer.train_step()
    trainer.state.timings.clear()
    start = time.perf_counter()
    for _ in range(steps):
        if threads is not None:
            threads.check()
        trainer.train_step()
    ms = 1000 * (time.perf_counter() - start) / steps
    return {
        "ms_per_step": round(ms, 2),
        **{k: round(1000 * v / steps, 2) for k, v in trainer.state.timings.items()},
    }


def dtype_rows(
    run: Path, work: Path, data: Path | None, steps: int, threads: int, blocks: int = 6
) -> list[dict]:
    """Late steps with the fields in bf16 (autocast) and in float32 (the fused MLPs where they apply),
    in alternate blocks of one process: each its fastest block (the host's drift cancels)."""
    torch.set_num_threads(threads)
    trainers = {}
    for dtype in ("bf16", "float32"):
        trainers[dtype] = trainer_at(run, work / dtype, 0.75, data)
        trainers[dtype].model.bf16 = dtype == "bf16"
    best: dict[str, dict] = {}
    for block in range(2 * blocks):
        dtype = ("bf16", "float32")[block % 2]
        timed = time_steps(trainers[dtype], max(20, steps // 4))
        if timed["ms_per_step"] < best.get(dtype, {"ms_per_step": float("inf")})["ms_per_step"]:
            best[dtype] = timed
    return [
        {"what": DTYPE_ROWS, "setting": f"{dtype}, {threads} thread(s)", **timed}
        for dtype, timed in best.items()
    ]


def record_notes(run: Path, rows: list[dict]) -> str:
    """The record's notes: what the rows time on ``run``, and how the fields' dtype rows were measured
    where ``rows`` has them."""
    notes = (
        f"Steps of the trained run {run} resumed at 3/4 of its steps, ms per step and its parts (fields, "
        "raster_forward with the loss, backward, optimizer); `speed_vs_alone` is the 1-view step alone over "
        "the step beside a process spinning on one core."
    )
    if any(row.get("what") == DTYPE_ROWS for row in rows):
        notes += (
            " The fields' dtype rows put bf16 autocast against float32 (the fused MLPs where they apply) in "
            "alternate blocks of one process, each its fastest."
        )
    return notes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--run", type=Path, required=True, help="a trained run folder (e.g. the demo's)")
    ap.add_argument("--data", type=Path, help="the run's scene folder, where it has moved")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    cores = torch.get_num_threads()
    rows = []
    for size in (128, 256):
        for threads in sorted({1, cores}):
            rows.append(
                {
                    "what": f"SSIM forward + backward, {size} px",
                    "setting": f"{threads} thread(s)",
                    "pytorch_msssim_ms": round(ssim_ms(ssim, size, threads), 3),
                    "native_ms": round(ssim_ms(training_ssim, size, threads), 3),
                }
            )
    torch.set_num_threads(cores)
    with tempfile.TemporaryDirectory() as tmp:
        for views in (1, 2, 3, 4):
            trainer = trainer_at(
                args.run, Path(tmp) / "run", 0.75, args.data, **{"stage2.views_per_step": views}
            )
            rows.append(
                {"what": "training step", "setting": f"{views} view(s)", **time_steps(trainer, args.steps)}
            )
        alone = rows[-4]["ms_per_step"]
        if this_machine().fast_bf16:  # (elsewhere bf16 is emulated, far slower)
            for threads in sorted({1, cores}):
                rows += dtype_rows(args.run, Path(tmp), args.data, args.steps, threads)
            torch.set_num_threads(cores)
        hog = subprocess.Popen([sys.executable, "-c", "while True: pass"])
        try:
            time.sleep(1.0)
            for label, count in ((f"{cores} threads, fixed", cores), ("chosen (train/threads.py)", 0)):
                trainer = trainer_at(args.run, Path(tmp) / "run", 0.75, args.data)
                with ThreadPolicy(count) as policy:
                    timed = time_steps(trainer, max(20, args.steps // 4), policy)
                rows.append(
                    {
                        "what": "training step beside a busy core",
                        "setting": label,
                        **timed,
                        "threads": torch.get_num_threads() if count else policy.changes[-1]["threads"],
                        "speed_vs_alone": round(alone / timed["ms_per_step"], 3),
                    }
                )
        finally:
            hog.kill()
            hog.wait()
    for row in rows:
        print(row)
    if args.json:
        record = make_record(
            "training-speed",
            rows,
            f"python benchmarks/training_speed.py --run {args.run}",
            title="Where a training step's time goes: SSIM, views per step, the fields' dtype, a busy core",
            notes=record_notes(args.run, rows),
        )
        write_record(args.json, record)


if __name__ == "__main__":
    main()
