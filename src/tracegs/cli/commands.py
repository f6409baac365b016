"""The flags of each ``tracegs`` command, one dataclass per command: tyro turns the field docstrings
into ``--help``, and the first line of the class docstring is the command's line in ``tracegs --help``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import tyro

from ..data.motion_masks import MotionMaskSettings
from ..segment.config import SegmentConfig

PresetName = Literal["paper", "cpu-fast", "capture", "tiny"]
"""The names of ``config.PRESETS``."""


@dataclass
class Demo:
    """Run the whole pipeline on a built-in scene: synthesise, train TRACE, evaluate, write a video.

    Writes the scene, the run, the metrics, rendered test frames and a time-sweep video under --out."""

    out: Path = Path("runs/demo")
    """Folder for the scene, the run and the results."""
    scene: str = "fan"
    """Built-in synthetic scene (see `tracegs synth --help`)."""
    preset: PresetName = "cpu-fast"
    """Training preset."""
    resolution: int = 128
    """Image size of the synthesised scene."""
    json: Path | None = None
    """Also write the demo's summary (metrics, files written) here."""
    device: str = "auto"
    """auto, cpu or cuda."""


@dataclass
class Synth:
    """Render a synthetic multi-part dynamic scene with ground-truth physics (Mitsuba 3)."""

    out: Path
    """Output scene folder (Blender/D-NeRF format plus gt/)."""
    scene: str = "fan"
    """fan, foldingchair, satellite, fallingball, slider (constant forces), pendulum, spring, brake, bounce,
    turntable (changing forces), rolling, gyroscope, doublependulum, planarsprings, collision (docs/SYNTH.md)."""
    resolution: int = 128
    views: int = 15
    frames: int = 60
    seed: int = 0
    sun: float = 2.0
    """Irradiance of the sun (directional light, hard shadows); 0 = no shading and no shadows."""
    ambient: float = 0.4
    """Radiance of a surface of albedo 1 lit by the ambient term alone."""
    textured_surroundings: bool = False
    """Also render a textured floor and walls round the scene, which a calibration (`tracegs import`) matches."""


@dataclass
class Train:
    """Train TRACE (--method defgs: the DefGS baseline, static: 3DGS) on a scene into a run folder.

    Every setting of the preset is a flag (`tracegs train --preset P --help` lists them with P's
    values); a killed run continues where it stopped when the same command runs again."""

    preset: PresetName = "cpu-fast"
    """The named config whose values are the defaults of every other flag."""
    json: Path | None = None
    """Also write the training summary here (it always goes to RUN/summary.json)."""
    resume: Path | None = None
    """Continue the run folder RUN with its own RUN/config.json (only --device may change)."""
    continual: bool = False
    """Continual learning: train on [0, --window], score the next --horizon, add --step, go on (continual.py)."""
    window: float = 0.15
    """--continual: the first round's observed span (a time in [0, 1], or frames with --frames)."""
    horizon: float = 0.15
    """--continual: the span predicted and scored after each round."""
    step: float | None = None
    """--continual: the span each round adds (default: --horizon)."""
    frames: bool = False
    """--continual: --window, --horizon and --step count frames."""
    fraction: float = 0.25
    """--continual: fraction of the stage-2 steps each round after the first trains (warm start)."""


@dataclass
class ResumeDevice:
    """The one flag `tracegs train --resume RUN` takes besides it."""

    device: str | None = None


@dataclass
class Calibrate:
    """Choose a run's post-training extrapolation state again: a run of an older tracegs, or new settings."""

    run: Path
    """Run folder written by `tracegs train`."""
    handover_frames: float | None = None
    """New ``extrapolation.handover_frames`` (default: the run's)."""
    free_bodies: bool | None = None
    """New ``extrapolation.free_bodies`` (default: the run's)."""
    joint_laws: bool | None = None
    """New ``extrapolation.joint_laws`` (default: the run's): the parts whose identified motion model
    beats the learned physics move by it; the report says per part what was tried and why."""
    surface_painters: Literal["edge", "hold"] | None = None
    """New ``extrapolation.surface_painters`` (default: the run's): moving Gaussians amid still ones (a
    shadow) move until they would leave their surface (``edge``), or ``hold`` still after the handover."""
    data: Path | None = None
    """Scene folder (default: the one the run was trained on)."""
    json: Path | None = None
    """Also write what the calibration chose here."""
    device: str = "auto"
    """auto, cpu or cuda."""


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
    """auto, cpu or cuda."""


@dataclass
class Eval:
    """Evaluate a run on the interpolation and extrapolation splits (the paper's protocol)."""

    run: Path
    """Run folder written by `tracegs train`."""
    data: Path | None = None
    """Scene folder (default: the one the run was trained on)."""
    json: Path | None = None
    """Write the metrics here (default: RUN/eval.json)."""
    out: Path | None = None
    """Folder of the rendered frames, OUT/interpolation/ and OUT/extrapolation/ (default: RUN/eval)."""
    half_res: bool = False
    """Score at half resolution."""
    lpips: bool = True
    """Compute LPIPS (VGG and AlexNet)."""
    save_images: bool = True
    """Write the rendered frames into --out."""
    until: float | None = None
    """Also render the new cameras' future up to this time past the data, scored while there are images."""
    motion: Literal["trace", "f_defo", "hold"] = "trace"
    """trace (the learned physics past the handover), f_defo (as DefGS) or hold (the span's end held still)."""
    moving_dilation: int | None = None
    """Pixels by which the masks of the moving pixels grow (default 3, eval/moving.py)."""
    device: str = "auto"
    """auto, cpu or cuda."""


@dataclass
class Export:
    """Export a run's Gaussians at any time as 3DGS PLY or .splat files, or its parts as MJCF and URDF.

    ``--time T`` writes one file, ``--times a:b:step`` a numbered sequence that splat editors play;
    ``--mjcf F`` / ``--urdf DIR`` its parts, joints and identified models for simulators (docs/EXPORT.md)."""

    run: Path
    """Run folder written by `tracegs train`."""
    mjcf: Path | None = None
    """Write a MuJoCo model (MJCF) of the run's parts and their models here, checked in MuJoCo."""
    urdf: Path | None = None
    """Write a URDF of them, with a mesh per part, into this folder."""
    time: float | None = None
    """The one time to export (t past the training span is predicted)."""
    times: str | None = None
    """A sequence START:STOP:STEP of times, written as NAME_0000.ply, NAME_0001.ply, ... and NAME.json."""
    ply: Path | None = None
    """The file of --time (default: RUN/export/gaussians_t<T>.ply); with --times its stem names the files."""
    out: Path | None = None
    """Folder of a --times sequence (default: RUN/export/sequence)."""
    format: Literal["ply", "splat", "both"] = "ply"
    """ply (3DGS PLY), splat (the web viewers' .splat) or both."""
    labels: bool = False
    """Colour the Gaussians by their segment (`tracegs segment` first)."""
    json: Path | None = None
    """Also write the export's report here."""
    device: str = "auto"
    """auto, cpu or cuda."""


@dataclass
class View:
    """Serve an interactive viewer of a run in the browser: any camera, a time slider into the future."""

    run: Path
    """Run folder written by `tracegs train`."""
    port: int = 8080
    """TCP port (a free one above it when it is taken)."""
    host: str = "127.0.0.1"
    """Address to listen on (0.0.0.0 serves other machines too)."""
    data: Path | None = None
    """Scene folder whose cameras are drawn (default: the one the run was trained on)."""
    t_end: float | None = None
    """End of the time slider (default: twice the training span's end)."""
    simulator: bool = False
    """Also offer the run's MuJoCo model (`tracegs export --mjcf`) as a motion, beside the learned one."""
    width: int = 320
    """Width in pixels of the rendered images."""
    device: str = "auto"
    """auto, cpu or cuda."""


@dataclass
class Segment:
    """Segment a trained run's Gaussians into objects and parts by their learned motion.

    K-means on the physics f_trd learned; stores the labels in the run folder, renders the masks at any
    time (future included), and scores them where the scene has ground-truth masks
    (docs/SEGMENTATION.md)."""

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
    """auto, cpu or cuda."""


@dataclass
class Masks:
    """Derive motion masks of a static rig's cameras from the capture: what differs from each camera's
    background plate (its frames' per-pixel median) moves.

    One PNG per frame under --out, the images' layout (255 = moves); --figure draws each camera's plate
    and masks. A capture whose cameras move has no plate, and is told so."""

    data: Path
    """Scene folder (Blender or Panoptic layout) whose cameras stand still."""
    out: Path
    """Folder of the masks: OUT/<the image's path under the scene folder, ims/ for Panoptic>.png."""
    split: str = "test"
    """The split whose frames are masked (each camera's plate is the median of its frames there)."""
    downscale: int = 1
    """Divide the image size by this integer factor (as `tracegs train --downscale`)."""
    figure: Path | None = None
    """Also write a PNG: per camera, a frame's image, the plate, and chosen frames with their masks."""
    figure_frames: tuple[int, ...] = ()
    """Indices of the frames the figure shows in each camera's frames (default: 1/4, 1/2, 3/4 through)."""
    json: Path | None = None
    """Also write the report (per camera: frames, share of moving pixels) here."""
    settings: MotionMaskSettings = field(default_factory=MotionMaskSettings)


@dataclass
class Import:
    """Turn a rig's synchronised videos (one per camera) into a calibrated scene (COLMAP) with motion masks."""

    out: Path
    """The scene folder to write (replaced only when a former import wrote it)."""
    videos: Path | None = None
    """Folder of the recordings: one video per camera, the camera named by the file's stem."""
    images: Path | None = None
    """Instead of --videos: a folder with one folder of frames (PNG, JPEG, in name order) per camera."""
    fps: float | None = None
    """Frames per second (default: the slowest video's rate); the rate of --images folders (default 30)."""
    start: float = 0.0
    """Seconds into the (lined up) recordings where the scene starts."""
    end: float | None = None
    """Seconds into the recordings where the scene ends (default: where the shortest ends)."""
    offsets: tuple[float, ...] = ()
    """Per camera (name order): seconds cut from its start to line the recordings up (started 0.5 s early: 0.5)."""
    downscale: int = 1
    """Divide the image size by this integer factor."""
    calibration: Path | None = None
    """Cameras from a COLMAP model folder, a nerfstudio transforms.json or a Dynamic 3D Gaussians meta."""
    calib_frames: int = 1
    """Frames per camera COLMAP calibrates on, spread over the span (more for a scene of little texture)."""
    camera_model: Literal["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV"] = "SIMPLE_RADIAL"
    """COLMAP's camera model, one per camera; the images of a model with distortion are undistorted."""
    scale: float | None = None
    """The cameras' median distance from where they look, e.g. in metres (default: 4 for COLMAP's; a file's own)."""
    val_cameras: tuple[str, ...] = ()
    """Cameras held out as the val split."""
    test_cameras: tuple[str, ...] = ()
    """Cameras held out as the test split."""
    drop_unregistered: bool = False
    """Write the scene without the cameras COLMAP cannot register (else it stops, naming them)."""
    json: Path | None = None
    """Also write the report here (it always goes to OUT/import.json)."""


@dataclass
class Metrics:
    """PSNR, SSIM and LPIPS of one pair of images."""

    image_a: tyro.conf.Positional[Path]
    image_b: tyro.conf.Positional[Path]
    json: Path | None = None
    """Also write the numbers here."""
    lpips: bool = True
    """Compute LPIPS (VGG and AlexNet)."""
    device: str = "auto"
    """auto, cpu or cuda."""


@dataclass
class Build:
    """Build the native CPU extensions now (rasteriser, SSIM, RK2, HexPlane), else each builds on first use.

    `scripts/install.sh` runs it. An extension that does not build is reported with the reason, and
    its PyTorch fallback runs instead (slower, same results)."""

    json: Path | None = None
    """Also write each extension's status here."""


@dataclass
class Bench:
    """Run a benchmark: `raster`, `fields`, `methods` (TRACE, TRACE_4dgs, DefGS) or `ablations` (Table 4).

    `--json docs/results/NAME.json` keeps the record for docs/RESULTS.md (`tracegs results`). `methods`
    and `ablations` train their rows one after the other; `--cluster auto` (or a Ray address) trains
    them side by side as Ray tasks of `--cpus-per-task` CPUs each."""

    what: tyro.conf.Positional[Literal["raster", "fields", "methods", "ablations"]]
    json: Path | None = None
    """Write the results record here (e.g. docs/results/methods.json)."""
    out: Path = Path("runs/bench")
    """Working folder for scenes and runs (train benchmark)."""
    preset: PresetName = "cpu-fast"
    scenes: tuple[str, ...] = ("fan",)
    """Synthetic scene names or scene folders (methods and ablations)."""
    resolution: int = 128
    """Image size of synthesised scenes."""
    dynamic_iterations: int | None = None
    """Override the preset's dynamic iterations (a shorter schedule for large tables)."""
    seed: int | None = None
    """Train the rows with this random seed (default: the preset's, 0); give each seed its own --out
    (a run folder made with another seed is set aside and trained again)."""
    variants: tuple[str, ...] = ()
    """Subset of rows to run (e.g. TRACE DefGS, or dt=1 "no f_defo"); empty = all of the paper's.
    The ablations also take our options beside the paper's switches (e.g. "no skip static")."""
    report_only: bool = False
    """Train nothing: tabulate the finished runs of these scenes and variants, skip the others."""
    device: str = "auto"
    """auto, cpu or cuda: where `raster` renders and `methods` / `ablations` train (auto: CUDA if present)."""
    isa: tuple[Literal["native", "avx2"], ...] = ("native",)
    """Instruction sets `raster` measures the CPU backends with, each in a process of its own: this CPU's
    (native), and avx2: held to an AVX2-only CPU's code paths (ATen, oneDNN, MKL, extensions built for
    x86-64-v3), as an AVX2 laptop runs; its rows time the native rasteriser only."""
    validation: float | None = None
    """Choose settings without the test splits: train on this fraction of the training span (e.g. 0.8)
    and score the training cameras' later frames (methods and ablations)."""
    cluster: str | None = None
    """Train the rows as Ray tasks (methods and ablations): `auto` starts a local Ray on every CPU, any
    other value is the address of a running Ray cluster (e.g. 10.0.0.5:6379); without it the rows train
    one after the other in this process, as before. Needs `pip install -e ".[cluster]"`."""
    cpus_per_task: int = 1
    """With --cluster: the CPUs of each row's training (its torch and OpenMP threads)."""


@dataclass
class Results:
    """Make docs/RESULTS.md (each benchmark's headline against its anchor) and one page per record,
    docs/results/NAME.md, from the results records docs/results/NAME.json."""

    json: Path = Path("docs/results")
    """Folder of the results records (``*.json``)."""
    out: Path = Path("docs/RESULTS.md")
    """The page to write."""
