"""``tracegs <command>``: the only argv parser (tyro). Each command is a plain function in the library.

Flag names are shared by every command: ``--data`` (a scene folder), ``--run`` (a run folder),
``--out`` (where outputs go), ``--json`` (write results as JSON), ``--preset`` (a named config).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro

COMMANDS = ("demo", "synth", "train", "render", "eval", "metrics", "bench")


@dataclass
class Demo:
    """Synthesise the default scene, train TRACE on it, extrapolate, evaluate, write images, video, metrics."""

    out: Path = Path("runs/demo")
    """Folder for the scene, the run and the results."""
    scene: str = "fan"
    """Built-in synthetic scene (see `tracegs synth --help`)."""
    preset: str = "cpu-fast"
    """Training preset."""
    resolution: int = 128
    """Image size of the synthesised scene."""
    device: str = "auto"
    """auto, cpu or cuda."""


@dataclass
class Synth:
    """Render a synthetic multi-part dynamic scene with ground-truth physics (Mitsuba 3)."""

    out: Path
    """Output scene folder (Blender/D-NeRF format plus gt/)."""
    scene: str = "fan"
    """fan, foldingchair, satellite, fallingball or slider."""
    resolution: int = 128
    views: int = 15
    frames: int = 60
    seed: int = 0
    sun: float = 2.0
    """Irradiance of the sun (directional light, hard shadows); 0 = no shading and no shadows."""
    ambient: float = 0.4
    """Radiance of a surface of albedo 1 lit by the ambient term alone."""


@dataclass
class Render:
    """Render a trained run at any time (t > 1 extrapolates with the learned physics), or a time-sweep video."""

    run: Path
    """Run folder written by `tracegs train`."""
    out: Path | None = None
    """Output PNG (one image) or MP4/GIF (with --video); default inside the run folder."""
    time: float = 1.0
    """Time to render (ignored with --video)."""
    camera: str = "test:0"
    """SPLIT:INDEX of a dataset camera (e.g. val:2), or 'orbit:DEG' for an orbit camera at azimuth DEG."""
    video: bool = False
    """Render a video with the camera sweeping around while time goes from 0 to --t-end."""
    t_end: float = 1.5
    """Last time of the video."""
    frames: int = 90
    """Frames of the video."""
    data: Path | None = None
    """Scene folder (default: the one the run was trained on)."""
    device: str = "auto"


@dataclass
class Eval:
    """Evaluate a run on the interpolation and extrapolation splits (the paper's protocol)."""

    run: Path
    data: Path | None = None
    """Scene folder (default: the one the run was trained on)."""
    json: Path | None = None
    """Write the metrics here (default: RUN/eval.json)."""
    half_res: bool = False
    """Score at half resolution."""
    lpips: bool = True
    """Compute LPIPS (VGG and AlexNet)."""
    save_images: bool = True
    """Write rendered test frames and side-by-side strips into RUN/eval/."""
    device: str = "auto"


@dataclass
class Metrics:
    """PSNR, SSIM and LPIPS of one pair of images."""

    image_a: tyro.conf.Positional[Path]
    image_b: tyro.conf.Positional[Path]
    json: Path | None = None


@dataclass
class Bench:
    """Benchmarks: `raster` (rasteriser backends), `fields` (MLP cost), `methods` (TRACE, TRACE_4dgs, DefGS),
    `ablations` (the paper's Table 4); tables go to docs/BENCHMARKS.md."""

    what: tyro.conf.Positional[Literal["raster", "fields", "methods", "ablations"]]
    json: Path | None = None
    """Write the records as JSON."""
    out: Path = Path("runs/bench")
    """Working folder for scenes and runs (train benchmark)."""
    preset: str = "cpu-fast"
    scenes: tuple[str, ...] = ("fan",)
    """Synthetic scene names or scene folders (methods and ablations)."""
    resolution: int = 128
    """Image size of synthesised scenes."""
    dynamic_iterations: int | None = None
    """Override the preset's dynamic iterations (a shorter schedule for large tables)."""
    variants: tuple[str, ...] = ()
    """Subset of rows to run (e.g. TRACE DefGS, or dt=1 "no f_defo"); empty = all of the paper's.
    The ablations also take our options beside the paper's switches (e.g. "skip static")."""
    report_only: bool = False
    """Train nothing: tabulate the finished runs of these scenes and variants, skip the others."""
    device: str = "auto"
    """auto, cpu or cuda: where `raster` renders and `methods` / `ablations` train (auto: CUDA if present)."""
    validation: float | None = None
    """Choose settings without the test splits: train on this fraction of the training span (e.g. 0.8)
    and score the training cameras' later frames (methods and ablations)."""


def _dump(result, path: Path | None, console: str | None = None) -> None:
    """Write ``result`` as JSON to ``path`` (if given) and print ``console``, or the JSON without it."""
    text = json.dumps(result, indent=2)
    if path is not None:
        from .utils import atomic_write_text

        atomic_write_text(path, text)
    print(text if console is None else console)


def run_train(argv: list[str]) -> dict:
    """`tracegs train --data D --run R [--preset P] [any config field]`; the preset sets the defaults."""
    from .config import TrainConfig, make_config
    from .train.trainer import Trainer

    preset = "cpu-fast"
    for i, arg in enumerate(argv):
        if arg == "--preset" and i + 1 < len(argv):
            preset = argv[i + 1]
        elif arg.startswith("--preset="):
            preset = arg.split("=", 1)[1]
    cfg = tyro.cli(TrainConfig, default=make_config(preset), args=argv, prog="tracegs train")
    cfg.preset = preset
    return Trainer(cfg).train()


def main(argv: list[str] | None = None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    if not argv or argv[0] in ("-h", "--help") or argv[0] not in COMMANDS:
        print("usage: tracegs {" + ",".join(COMMANDS) + "} [--help]\n")
        print(__doc__)
        sys.exit(0 if not argv or argv[0] in ("-h", "--help") else 2)
    command, rest = argv[0], argv[1:]
    prog = f"tracegs {command}"
    if command == "train":
        print(json.dumps(run_train(rest), indent=2))
    elif command == "demo":
        from .demo import run_demo

        args = tyro.cli(Demo, args=rest, prog=prog)
        run_demo(args.out, args.scene, args.preset, args.resolution, args.device)
    elif command == "synth":
        from .data.synth import synthesize

        a = tyro.cli(Synth, args=rest, prog=prog)
        synthesize(a.scene, a.out, a.resolution, a.views, a.frames, a.seed, sun=a.sun, ambient=a.ambient)
    elif command == "render":
        from .export.render import render_command

        a = tyro.cli(Render, args=rest, prog=prog)
        path = render_command(a.run, a.out, a.time, a.camera, a.video, a.t_end, a.frames, a.data, a.device)
        print(path)
    elif command == "eval":
        from .eval.protocol import evaluate_run

        a = tyro.cli(Eval, args=rest, prog=prog)
        from .eval.report import format_summary

        result = evaluate_run(a.run, a.data, a.half_res, a.lpips, a.save_images, a.device)
        path = a.json or a.run / "eval.json"
        _dump(result, path, console=format_summary(result) + f"\nall numbers: {path}")
    elif command == "metrics":
        from .eval.metrics import compare_images

        a = tyro.cli(Metrics, args=rest, prog=prog)
        _dump(compare_images(a.image_a, a.image_b), a.json)
    elif command == "bench":
        a = tyro.cli(Bench, args=rest, prog=prog)
        if a.what == "raster":
            from .render.bench import run_raster_bench

            records = run_raster_bench(json_path=a.json, device=a.device)
        else:
            from .bench import ABLATIONS, METHODS, OPTIONS, run_field_bench, run_variant_table

            if a.what == "fields":
                records = run_field_bench()
            else:
                table = METHODS if a.what == "methods" else ABLATIONS
                known = table if a.what == "methods" else ABLATIONS | OPTIONS
                unknown = set(a.variants) - set(known)
                if unknown:
                    raise SystemExit(f"unknown variants {sorted(unknown)}; choose from {list(known)}")
                variants = {k: v for k, v in known.items() if k in a.variants} if a.variants else table
                overrides = {} if a.device == "auto" else {"device": a.device}
                if a.dynamic_iterations is not None:
                    overrides["dynamic_iterations"] = a.dynamic_iterations
                records = run_variant_table(
                    a.what,
                    variants,
                    a.out,
                    a.scenes,
                    a.preset,
                    a.resolution,
                    overrides,
                    train=not a.report_only,
                    validation=a.validation,
                )
            if a.json is not None:
                _dump(records, a.json)
        print(json.dumps(records, indent=2)[:4000])


if __name__ == "__main__":
    main()
