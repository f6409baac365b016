"""`tracegs demo`: the whole method on a built-in scene, from nothing to metrics and a video."""

from __future__ import annotations

import json
from pathlib import Path

from .config import make_config
from .utils import atomic_write_text


def run_demo(
    out: Path = Path("runs/demo"),
    scene: str = "fan",
    preset: str = "cpu-fast",
    resolution: int = 128,
    device: str = "auto",
) -> dict:
    """Synthesise ``scene``, train TRACE with ``preset``, extrapolate, evaluate; returns the metrics."""
    from .data.synth import synthesize
    from .eval.protocol import evaluate_run
    from .eval.report import format_summary
    from .export.render import render_command
    from .train.trainer import Trainer

    out = Path(out)
    data = out / "scene"
    if not (data / "transforms_test.json").is_file():
        print(f"[1/4] synthesising scene '{scene}' at {resolution} px into {data}")
        synthesize(scene, data, resolution=resolution)
    run = out / "trace"
    print(f"[2/4] training TRACE ({preset}) into {run}")
    cfg = make_config(preset, data=data, run=run, device=device)
    summary = Trainer(cfg).train()
    print("[3/4] evaluating interpolation and extrapolation")
    metrics = evaluate_run(run, device=device)
    atomic_write_text(run / "eval.json", json.dumps(metrics, indent=2))
    print("[4/4] rendering a video sweeping time 0 -> 1.5")
    video = render_command(run, video=True, t_end=1.5, device=device)
    result = {
        "train_seconds": summary["train_seconds"],
        "gaussians": summary["gaussians"],
        "interpolation_psnr": metrics["interpolation"].get("mae_psnr"),
        "extrapolation_psnr": metrics["extrapolation"].get("mae_psnr"),
        "extrapolation_ssim": metrics["extrapolation"].get("ssim"),
        "extrapolation_lpips_vgg": metrics["extrapolation"].get("lpips_vgg"),
        "video": str(video),
        "metrics": str(run / "eval.json"),
        "renders": str(run / "eval"),
    }
    print(format_summary(metrics))
    print(f"all numbers: {run / 'eval.json'}\nrendered test frames: {run / 'eval'}\nvideo: {video}")
    return result
