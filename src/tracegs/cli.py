"""``tracegs <command>``: the only argv parser (tyro). Each command is a plain function in the library.

Flag names are shared by every command: ``--data`` (a scene folder), ``--run`` (a run folder),
``--out`` (where outputs go), ``--json`` (write results as JSON), ``--preset`` (a named config).
"""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import tyro

from .segment.config import SegmentConfig

if TYPE_CHECKING:
    from .config import TrainConfig

COMMANDS = ("demo", "synth", "train", "calibrate", "render", "eval", "segment", "metrics", "bench", "results")


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
class Calibrate:
    """Choose a trained run's post-training extrapolation state again on its training images (the
    handover's still Gaussians, the free bodies) and store it: for a run written by an older tracegs,
    or after changing an extrapolation setting (e.g. ``--free-bodies False``)."""

    run: Path
    """Run folder written by `tracegs train`."""
    handover_frames: float | None = None
    """New ``extrapolation.handover_frames`` (default: the run's)."""
    free_bodies: bool | None = None
    """New ``extrapolation.free_bodies`` (default: the run's)."""
    data: Path | None = None
    """Scene folder (default: the one the run was trained on)."""
    device: str = "auto"


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
class Segment:
    """Segment a trained run's Gaussians by their learned motion (K-means on the physics f_trd learned),
    store the labels in the run folder, render the masks at any time (future included), and score them
    where the scene has ground-truth masks (docs/SEGMENTATION.md)."""

    run: Path
    """Run folder written by `tracegs train`."""
    k: int | None = None
    """Number of segments, the static group counted."""
    auto_k: bool = False
    """Choose K without labels (the smallest K whose segments all move rigidly; see --help of settings)."""
    data: Path | None = None
    """Scene folder (default: the one the run was trained on)."""
    time: float | None = None
    """Time of the mask images and the coloured PLY (default: the last training time; t > 1 extrapolates)."""
    json: Path | None = None
    """Also write the report here (it always goes to OUT/segment.json)."""
    out: Path | None = None
    """Folder of the images, PLY, video and report (default: RUN/segment, RUN/segment-flow)."""
    video: bool = False
    """Also write OUT/sweep.mp4: an orbit while time runs 0 -> 1.5, the segments painted over it."""
    score: bool = True
    """Score against the scene's ground truth when it has some."""
    ignore_pixels: int = 0
    """Leave ground-truth segments smaller than this many pixels out of the scores (OGC's
    ignore_npoint_thresh; 0 scores every one)."""
    settings: SegmentConfig = field(default_factory=SegmentConfig)
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
    `ablations` (the paper's Table 4). `--json docs/results/NAME.json` keeps the record for
    docs/RESULTS.md (`tracegs results`)."""

    what: tyro.conf.Positional[Literal["raster", "fields", "methods", "ablations"]]
    json: Path | None = None
    """Write the results record here (e.g. docs/results/methods.json)."""
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
    The ablations also take our options beside the paper's switches (e.g. "no skip static")."""
    report_only: bool = False
    """Train nothing: tabulate the finished runs of these scenes and variants, skip the others."""
    device: str = "auto"
    """auto, cpu or cuda: where `raster` renders and `methods` / `ablations` train (auto: CUDA if present)."""
    validation: float | None = None
    """Choose settings without the test splits: train on this fraction of the training span (e.g. 0.8)
    and score the training cameras' later frames (methods and ablations)."""


@dataclass
class Results:
    """Make docs/RESULTS.md from the results records in docs/results/ (one table per benchmark)."""

    json: Path = Path("docs/results")
    """Folder of the results records (``*.json``)."""
    out: Path = Path("docs/RESULTS.md")
    """The page to write."""


@dataclass
class _PresetChoice:
    """The first pass of ``tracegs train``: which preset gives the defaults of the full parse."""

    preset: Literal["paper", "cpu-fast", "tiny"] = "cpu-fast"


def _dump(result, path: Path | None, console: str | None = None) -> None:
    """Write ``result`` as JSON to ``path`` (if given) and print ``console``, or the JSON without it."""
    text = json.dumps(result, indent=2)
    if path is not None:
        from .utils import atomic_write_text

        atomic_write_text(path, text)
    print(text if console is None else console)


def train_config(argv: list[str]) -> TrainConfig:
    """The config of `tracegs train --data D --run R [--preset P] [--section.field V ...]`: tyro reads
    ``--preset`` first (``return_unknown_args``), then every flag with that preset's values as the
    defaults (tyro's pattern for overridable configs); ``--help`` shows the preset's values."""
    from .config import PRESETS

    choice, _ = tyro.cli(_PresetChoice, args=argv, return_unknown_args=True, add_help=False)
    default = PRESETS[choice.preset]()
    cfg = tyro.cli(type(default), default=default, args=argv, prog="tracegs train")
    cfg.preset = choice.preset
    return cfg


def run_train(argv: list[str]) -> dict:
    """`tracegs train`: train the run that ``train_config(argv)`` describes."""
    from .train.trainer import Trainer

    return Trainer(train_config(argv)).train()


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
    elif command == "calibrate":
        from .run import calibrate_run

        a = tyro.cli(Calibrate, args=rest, prog=prog)
        settings = {
            f"extrapolation.{k}": v
            for k, v in (("handover_frames", a.handover_frames), ("free_bodies", a.free_bodies))
            if v is not None
        }
        state = calibrate_run(a.run, a.device, settings, a.data)
        print(json.dumps({"freeze_threshold": state.freeze_threshold, **state.report}, indent=2))
    elif command == "results":
        from .results import write_results_page

        a = tyro.cli(Results, args=rest, prog=prog)
        print(write_results_page(a.json, a.out))
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
    elif command == "segment":
        from .segment.command import segment_run
        from .segment.report import format_report

        a = tyro.cli(Segment, args=rest, prog=prog)
        report = segment_run(
            a.run,
            a.data,
            a.k,
            a.auto_k,
            a.time,
            a.json,
            a.out,
            a.video,
            a.settings,
            a.score,
            a.device,
            a.ignore_pixels,
        )
        print(format_report(report))
    elif command == "metrics":
        from .eval.metrics import compare_images

        a = tyro.cli(Metrics, args=rest, prog=prog)
        _dump(compare_images(a.image_a, a.image_b), a.json)
    elif command == "bench":
        _bench(tyro.cli(Bench, args=rest, prog=prog))


def _bench(a: Bench) -> None:
    """`tracegs bench WHAT`: one benchmark; its record goes to ``--json`` when given."""
    from .bench import ABLATIONS, METHODS, OPTIONS, run_field_bench, run_raster_bench, run_variant_table

    if a.what == "raster":
        records = run_raster_bench(json_path=a.json, device=a.device)
    elif a.what == "fields":
        records = run_field_bench(json_path=a.json)
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
            json_path=a.json,
        )
    print(json.dumps(records, indent=2)[:4000])


if __name__ == "__main__":
    main()
