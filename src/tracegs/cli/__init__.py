"""``tracegs <command>``: the only argv parser (tyro). Each command is a plain function in the library.

Flag names are shared by every command: ``--data`` (a scene folder), ``--run`` (a run folder),
``--out`` (where outputs go), ``--json`` (write results as JSON), ``--preset`` (a named config),
``--device`` (auto, cpu or cuda). A rejected input (a malformed scene, run folder or flag) ends the
command with one line on stderr, ``tracegs COMMAND: error: MESSAGE``, and exit status 1 (2 for a
usage error, 130 for Ctrl-C); ``--debug`` anywhere on the command line shows the traceback instead. An
error that no check of ours raised is a bug: its traceback is printed, with a line that says so.
"""

from __future__ import annotations

import json
import sys
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import tyro

from .commands import (
    Bench,
    Build,
    Calibrate,
    Demo,
    Eval,
    Export,
    Import,
    Masks,
    Metrics,
    Render,
    Results,
    ResumeDevice,
    Segment,
    Synth,
    Train,
    View,
)

if TYPE_CHECKING:
    from ..config import TrainConfig


# ----- the commands -------------------------------------------------------------------------------
def _dump(result, path: Path | None, console: str | None = None) -> None:
    """Write ``result`` as JSON to ``path`` (if given) and print ``console``, or the JSON without it."""
    text = json.dumps(result, indent=2)
    if path is not None:
        from ..utils import atomic_write_text

        atomic_write_text(path, text)
    print(text if console is None else console)


def check_device(name: str) -> str:
    """``name`` when it is a device this machine has (auto, cpu, cuda, cuda:INDEX); else a ValueError
    naming ``--device``, before anything is read or trained."""
    import torch

    if name == "auto":
        return name
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        device = None
    if device is None or device.type not in ("cpu", "cuda"):
        raise ValueError(f"--device {name!r}: expected auto, cpu, cuda or cuda:INDEX")
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"--device {name}: CUDA is not available on this machine (use auto or cpu)")
    if device.type == "cuda" and (device.index or 0) >= torch.cuda.device_count():
        raise ValueError(f"--device {name}: this machine has {torch.cuda.device_count()} CUDA devices")
    return name


def _parse(cls, argv: list[str], prog: str):
    """``argv`` as a ``cls`` (tyro), its ``device`` (when it has one) checked."""
    args = tyro.cli(cls, args=argv, prog=prog)
    if isinstance(getattr(args, "device", None), str):
        check_device(args.device)
    return args


def _flag_given(argv: list[str], flag: str) -> bool:
    return any(a == flag or a.startswith(flag + "=") for a in argv)


def _train_request(argv: list[str]) -> tuple[TrainConfig, Train]:
    """The config that `tracegs train ARGV` trains and the command's own flags (``Train``): tyro reads
    ``--preset`` first (``return_unknown_args``), then every flag with that preset's values as the
    defaults (``--help`` shows them). The config is checked (``config.validate``), its paths made
    absolute (a run is read from any folder)."""
    from ..config import PRESETS, validate
    from ..run import CONFIG, load_config

    flags, rest = tyro.cli(Train, args=argv, return_unknown_args=True, add_help=False)
    if flags.resume is not None:
        others = [a for a in rest if a.startswith("-") and not _flag_given([a], "--device")]
        if others or _flag_given(argv, "--preset"):
            given = others or ["--preset"]
            raise ValueError(
                f"--resume takes no other training flag (got {given[0]}): the run continues with its own "
                f"{flags.resume / CONFIG}; only --device may change"
            )
        device = tyro.cli(ResumeDevice, args=rest, prog="tracegs train").device
        cfg = load_config(flags.resume / CONFIG)
        cfg.run = flags.resume
        if device is not None:
            cfg.device = device
    else:
        default = PRESETS[flags.preset]()
        description = (
            _description(Train)
            + "\n\n--json FILE also writes the summary to FILE; --resume RUN continues RUN; --continual trains "
            "in rounds (--window W --horizon H [--step S --frames --fraction F]: observe [0, W], predict the next "
            "H, add S, go on; RUN/continual.json)."
        )
        cfg = tyro.cli(
            type(default), default=default, args=rest, prog="tracegs train", description=description
        )
        cfg.preset = flags.preset
    cfg.data, cfg.run = Path(cfg.data).absolute(), Path(cfg.run).absolute()
    check_device(cfg.device)
    return validate(cfg), flags


def run_train(argv: list[str]) -> dict:
    """`tracegs train`: train the run that ``_train_request(argv)`` describes (or ``--resume RUN``)."""
    from ..train.trainer import Trainer

    cfg, flags = _train_request(argv)
    if flags.continual:
        from ..continual import Continual, train_continual

        summary = train_continual(
            cfg, Continual(flags.window, flags.horizon, flags.step, flags.frames, flags.fraction)
        )
    else:
        summary = Trainer(cfg).train()
    _dump(summary, flags.json)
    return summary


def _demo(a: Demo) -> None:
    from ..demo import run_demo

    result = run_demo(a.out, a.scene, a.preset, a.resolution, a.device)
    if a.json is not None:
        _dump(result, a.json, console=f"summary: {a.json}")


def _synth(a: Synth) -> None:
    from ..data.synth import synthesize

    synthesize(
        a.scene, a.out, a.resolution, a.views, a.frames, a.seed, sun=a.sun, ambient=a.ambient,
        textured_surroundings=a.textured_surroundings,
    )  # fmt: skip


def _calibrate(a: Calibrate) -> None:
    from ..config import check_setting, flag_name
    from ..run import calibrate_run

    settings = {
        f"extrapolation.{k}": v
        for k, v in (
            ("handover_frames", a.handover_frames),
            ("free_bodies", a.free_bodies),
            ("joint_laws", a.joint_laws),
            ("surface_painters", a.surface_painters),
        )
        if v is not None
    }
    for name, value in settings.items():
        check_setting(name, value, flag_name(name.split(".", 1)[1]))
    state = calibrate_run(a.run, a.device, settings, a.data)
    _dump({"freeze_threshold": state.freeze_threshold, **state.report}, a.json)


def _results(a: Results) -> None:
    from ..results import write_results_page

    print(write_results_page(a.json, a.out))


def _render(a: Render) -> None:
    from ..export.render import render_command

    print(render_command(a.run, a.out, a.time, a.camera, a.video, a.t_end, a.frames, a.data, a.device))


def _eval(a: Eval) -> None:
    from ..eval.protocol import evaluate_run
    from ..eval.report import format_summary

    result = evaluate_run(
        a.run, a.data, a.half_res, a.lpips, a.save_images, a.device, out=a.out, motion=a.motion,
        moving_dilation=a.moving_dilation,
    )  # fmt: skip
    console = format_summary(result)
    if a.until is not None:  # the new cameras past the data (``eval/horizon.py``)
        from ..eval.horizon import long_horizon

        out = None if a.out is None else a.out / "horizon"
        result["horizon"] = long_horizon(a.run, a.until, a.data, device=a.device, out=out)
        console += f"\nlong horizon to t = {a.until:g}: {result['horizon']['note']}"
    path = a.json or a.run / "eval.json"
    _dump(result, path, console=console + f"\nall numbers: {path}")


def _export(a: Export) -> None:
    from ..export.command import export_run
    from ..export.simulator import export_simulator, format_report

    if a.mjcf is None and a.urdf is None:
        return _dump(export_run(a.run, a.time, a.times, a.ply, a.out, a.format, a.labels, a.device), a.json)
    report = export_simulator(a.run, a.mjcf, a.urdf, a.device)
    _dump(report, a.json, format_report(report))


def _view(a: View) -> None:
    from ..view.server import serve

    serve(a.run, a.port, a.host, a.data, a.device, t_end=a.t_end, width=a.width, simulator=a.simulator)


def _segment(a: Segment) -> None:
    from ..segment.command import segment_run
    from ..segment.report import format_report

    report = segment_run(
        a.run, a.data, a.k, a.auto_k, a.time, a.json, a.out, a.video, a.settings, a.score, a.device, a.ignore_pixels
    )  # fmt: skip
    print(format_report(report))


def _masks(a: Masks) -> None:
    from ..data.motion_masks import format_report, write_motion_masks

    report = write_motion_masks(a.data, a.split, a.out, a.downscale, a.settings, a.figure, a.figure_frames)
    _dump(report, a.json, format_report(report))


def _import(a: Import) -> None:
    from ..data.importer import format_report, import_scene

    report = import_scene(**{k: v for k, v in vars(a).items() if k != "json"})
    _dump(report, a.json, format_report(report))


def _metrics(a: Metrics) -> None:
    from ..eval.metrics import compare_images

    _dump(compare_images(a.image_a, a.image_b, "cpu" if a.device == "auto" else a.device, a.lpips), a.json)


def _build(a: Build) -> None:
    """`tracegs build`: every native extension built (or found in the cache), each one's status."""
    from ..cpp import build_all, format_build_report

    report = build_all()
    _dump(report, a.json, format_build_report(report))


def _bench(a: Bench) -> None:
    """`tracegs bench WHAT`: one benchmark; its record goes to ``--json`` when given."""
    from ..bench.command import bench_command

    print(json.dumps(bench_command(a), indent=2)[:4000])


COMMANDS: dict[str, tuple[type, Callable]] = {
    "demo": (Demo, _demo),
    "synth": (Synth, _synth),
    "train": (Train, None),
    "calibrate": (Calibrate, _calibrate),
    "render": (Render, _render),
    "eval": (Eval, _eval),
    "export": (Export, _export),
    "view": (View, _view),
    "segment": (Segment, _segment),
    "masks": (Masks, _masks),
    "import": (Import, _import),
    "metrics": (Metrics, _metrics),
    "bench": (Bench, _bench),
    "build": (Build, _build),
    "results": (Results, _results),
}
"""Each command: the dataclass of its flags (its docstring's first line is its line in ``tracegs
--help``) and the function that runs it (``train`` parses its config itself: ``run_train``)."""


USER_ERRORS = (ValueError, OSError)
"""What a rejected input raises: the project's DatasetError and RunError (both ValueError), ValueError
for a bad setting, OSError (FileNotFoundError, NotADirectoryError, IsADirectoryError, PermissionError,
a full disk) for the file system's refusals. Anything else is a bug."""


def _description(cls: type) -> str:
    return " ".join((cls.__doc__ or "").split("\n\n")[0].split())


def _summary(cls: type) -> str:
    """The first line of a command's docstring, its line in ``tracegs --help``."""
    return (cls.__doc__ or "").strip().split("\n")[0]


def usage() -> str:
    """``tracegs --help``: every command with its one-line description, and the shared flags."""
    width = max(map(len, COMMANDS))
    lines = [f"  {name:<{width}}  {_summary(cls)}" for name, (cls, _) in COMMANDS.items()]
    return "\n".join(
        [
            "usage: tracegs COMMAND [FLAGS] [--debug]",
            "",
            "TRACE: learn a dynamic 3D Gaussian scene and its physics from videos, and predict the future.",
            "",
            "commands:",
            *lines,
            "",
            "Shared flags: --data (a scene folder), --run (a run folder), --out (where outputs go), --json",
            "(write results as JSON), --preset (paper, cpu-fast, capture, tiny), --device (auto, cpu, cuda).",
            "`tracegs COMMAND --help` lists a command's flags; --debug shows the traceback of an error.",
        ]
    )


def error_message(err: BaseException) -> str:
    """An exception as one line: the file and the OS's words for an OSError, else its message."""
    if isinstance(err, OSError) and err.filename is not None and err.strerror:
        return f"{err.filename}: {err.strerror}"
    text = " ".join(str(err).split())
    return text or type(err).__name__


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so that the interpreter's last flush does not fail on the closed pipe."""
    import os

    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError):  # no file descriptor (stdout replaced in-process)
        pass


def run_command(command: str, argv: list[str]) -> None:
    """Parse ``argv`` for ``command`` and run it; errors propagate (``main`` reports them)."""
    prog = f"tracegs {command}"
    if command == "train":
        run_train(argv)
        return
    cls, handler = COMMANDS[command]
    handler(_parse(cls, argv, prog))


def main(argv: list[str] | None = None) -> None:
    """``tracegs COMMAND ...`` (the console script); ``argv`` defaults to ``sys.argv[1:]``."""
    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv
    argv = [a for a in argv if a != "--debug"]
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        sys.exit(0)
    command, rest = argv[0], argv[1:]
    if command not in COMMANDS:
        print(
            f"tracegs: error: unknown command {command!r}; choose from {', '.join(COMMANDS)}", file=sys.stderr
        )
        sys.exit(2)
    prog = f"tracegs {command}"
    try:
        run_command(command, rest)
    except KeyboardInterrupt:
        if debug:
            raise
        print(f"{prog}: interrupted", file=sys.stderr)
        sys.exit(130)
    except BrokenPipeError:  # whoever read the output stopped reading (`| head`): nothing to report
        _silence_stdout()
        sys.exit(141)
    except USER_ERRORS as err:
        if debug:
            raise
        print(f"{prog}: error: {error_message(err)}", file=sys.stderr)
        sys.exit(1)
    except Exception as err:
        if debug:
            raise
        traceback.print_exc()
        print(
            f"{prog}: error: this is a bug in tracegs, please report it with the traceback above "
            f"({type(err).__name__}: {error_message(err)})",
            file=sys.stderr,
        )
        sys.exit(1)


if __name__ == "__main__":
    main()
