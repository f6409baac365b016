"""Typed configuration of a training run, and the named presets.

Every constant of the method is a field here (or in the field configs it nests), with a docstring
that tyro turns into ``--help``. Sections: ``optim`` (learning rates, loss), ``densify`` (adaptive
density control), ``deformation`` (f_defo), ``dynamics`` (f_trd), ``stage2`` (how stage 2 trains the
fields, with the paper's Table 4 switches) and ``extrapolation`` (what happens after training: the
handover, what holds still, free bodies; read after the last step and when rendering, never in
training). The model's sections are defined beside its code in ``models/``, and the model is handed
only what it reads (``TrainConfig.model_config``). Why each preset value is what it is: docs/DESIGN.md; the numbers behind it: docs/RESULTS.md.
A run folder holds the resolved config as ``config.json`` (``run.py``; plain JSON, never ``eval``).
``validate(cfg)`` (``config/validate.py``) checks every setting before anything is trained.
"""

from __future__ import annotations

import copy
import dataclasses
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from ..extrapolate.settings import ExtrapolationConfig
from ..machine import this_machine
from ..models.config import ModelConfig, Stage2Config
from ..models.deformation import DeformationConfig
from ..models.dynamics import DynamicsConfig
from .sections import DensifyConfig, OptimConfig
from .validate import check_setting, flag_name, validate  # noqa: F401  (part of the config API)


@dataclass
class TrainConfig:
    """A TRACE (or DefGS baseline) training run."""

    data: Path = Path("data/scene")
    """Scene folder in Blender/D-NeRF format (transforms_train.json, ...)."""
    run: Path = Path("runs/scene")
    """Output folder: checkpoints, config, logs, renders."""
    method: Literal["trace", "defgs", "static"] = "trace"
    """trace = deformation + dynamics; defgs = deformation field alone; static = 3DGS at t = 0 only."""
    preset: str = "paper"
    """The named preset whose values are the defaults of every other setting: paper, cpu-fast,
    capture (a real rig's video) or tiny (``config.PRESETS``); recorded in the run folder."""
    device: str = "auto"
    """'auto' (CUDA if present, else CPU), 'cpu' or 'cuda[:i]'."""
    threads: int = 0
    """CPU threads of the training; 0: one per core that other processes leave free, counted at the
    start and every 30 s (``train/threads.py``; ``OMP_NUM_THREADS``, when set, is kept)."""
    seed: int = 0  # random seed
    downscale: int = 1  # integer factor by which images are downscaled when loaded
    t_train_end: float | None = None
    """Only training frames with time <= this are used (None: the dataset's value, else all)."""
    arriving_frames: bool = False
    """Also train on the frames the training cameras took in the scene's other splits (up to
    ``t_train_end``): continual learning's rounds, where the same cameras keep filming."""
    static_iterations: int = 3000
    """Stage 1: static 3DGS on the frames at t = 0."""
    dynamic_iterations: int = 37000
    """Stage 2: deformation + dynamics on all training frames (the paper runs 40k in total); steps of
    ``stage2.views_per_step`` views, more where fewer cameras saw each time."""
    init_points: int = 100_000
    """Random initial Gaussians in the scene bounds (when the dataset has no points)."""
    init_extent: float = 1.3
    """Half-size of the random-init cube when the dataset gives no aabb, for cameras 4.03 units from
    the point they look at (the Blender / D-NeRF layout); scaled with that distance (``init_box``)."""
    init_box: Literal["cameras", "origin"] = "cameras"
    """Where the random-init cube lies when the dataset gives no aabb or points: ``cameras`` centres
    it on the point the cameras look at and scales it with their distance (any capture's scale);
    ``origin``: +/- ``init_extent`` around the origin. Forward-facing captures fall back to ``origin``."""
    init_hull: bool = False
    """Add Gaussians on the visual hull of the first time's foreground masks, carved in that cube
    (``data/masks.py``, ``data/hull.py``; none without masks). ``hull_resolution``: voxels a side."""
    hull_resolution: int = 96
    init_surroundings: int = 0
    """Add Gaussians on the static surroundings of an inward-facing capture (the walls and floor
    behind its subject): this many directions from the point the cameras look at, each at the distance
    where the first time's cameras agree best on its colour (``data/surroundings.py``); 0 = none."""
    camera_colour: bool = False
    """Learn a gain and an offset per colour channel for each training camera (``models/colour.py``), as
    Dynamic 3D Gaussians does for a real rig; cameras never trained (the test cameras) render unmapped."""
    field_frame: Literal["auto", "cameras", "world"] = "auto"
    """The frame the fields see positions in (``train/scene_frame.py``): ``world`` coordinates (the
    paper's), or the ``cameras``' frame (centred where they look, scaled by their distance against the
    Blender layout's 4.03) for a capture in any units; ``auto``: the world's when the scene already lies
    within a few units of the origin, else the cameras'."""
    near_plane: float = 0.01
    """Gaussians nearer a camera than this are not drawn, in the units of ``init_extent`` (scaled with
    the cameras' distance from the point they look at; the Blender layout's scene units)."""
    sh_degree: int = 3  # maximum spherical-harmonics degree
    sh_degree_interval: int = 1000
    """Raise the active SH degree by one every this many steps."""
    bf16: bool = False
    """Run the fields under bfloat16 autocast on CPU (helps on CPUs with AMX or AVX512-BF16; ``cpu-fast`` sets
    it there). Training follows it; rendering and evaluation use it only on such a CPU (elsewhere fp32 is
    faster and exact). Ignored on CUDA."""
    random_background: bool = False
    """Composite RGBA training images on a random colour each step (discourages floaters that
    imitate the background); images without alpha are unaffected."""
    backend: str = "auto"
    """Rasteriser backend: auto, native, reference or gsplat."""
    checkpoint_every: int = 2000
    """Write a checkpoint every this many steps (and at the end); a killed run resumes from it."""
    log_every: int = 100  # log losses and timings every this many steps
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    deformation: DeformationConfig = field(default_factory=DeformationConfig)
    """f_defo, the auxiliary deformation field."""
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    """f_trd, the translation-rotation dynamics field."""
    stage2: Stage2Config = field(default_factory=Stage2Config)
    extrapolation: ExtrapolationConfig = field(default_factory=ExtrapolationConfig)

    @property
    def total_iterations(self) -> int:
        return self.static_iterations + (0 if self.method == "static" else self.dynamic_iterations)

    def model_config(self) -> ModelConfig:
        """The settings of this run's model (``TraceModel``): its sections, shared with this config."""
        return ModelConfig(
            method=self.method,
            deformation=self.deformation,
            dynamics=self.dynamics,
            stage2=self.stage2,
            sh_degree=self.sh_degree,
            backend=self.backend,
            camera_colour=self.camera_colour,
            bf16=self.bf16,
        )


def paper() -> TrainConfig:
    """The paper's sizes: 8 x 256 fields, 3k static + 37k dynamic iterations, SH degree 3."""
    return TrainConfig(preset="paper")


def cpu_fast() -> TrainConfig:
    """Minutes on 2 CPU cores at ~128 px: small fields, bf16 where the CPU has it, a Gaussian budget, fields
    that skip the Gaussians standing still, free bodies for the parts in flight (docs/DESIGN.md)."""
    return TrainConfig(
        preset="cpu-fast",
        static_iterations=1500,
        dynamic_iterations=20000,
        bf16=this_machine().fast_bf16,
        random_background=True,
        init_points=5000,
        sh_degree=1,
        sh_degree_interval=500,
        checkpoint_every=1000,
        optim=OptimConfig(field_lr_final=1.6e-5),
        densify=DensifyConfig(
            refine_start=300, refine_stop=4500, refine_every=100, reset_every=3000, max_gaussians=7_000
        ),
        deformation=DeformationConfig(depth=4, width=64, skip_layer=2),
        dynamics=DynamicsConfig(
            depth=4,
            width=64,
            num_frequencies=6,
            time_frequencies=3,
            acceleration_depth=2,
            angular_accelerations_from_head=True,
            detach_acceleration_features=True,
        ),
        stage2=Stage2Config(acceleration_consistency=0.01, consistency_frames=8.0, skip_static=True),
        extrapolation=ExtrapolationConfig(free_bodies=True, joint_laws=True),
    )


def capture() -> TrainConfig:
    """A real multi-view capture at ~320 x 180 px (a rig of inward-facing cameras round a subject, with
    or without foreground masks): ``cpu-fast`` with Gaussians started on the masks' visual hull and on
    the surroundings, a per-camera colour, and a budget for a room rather than an object."""
    cfg = cpu_fast()
    cfg.preset = "capture"
    cfg.init_hull, cfg.init_surroundings, cfg.init_points, cfg.init_extent = True, 20_000, 2000, 2.6
    cfg.camera_colour, cfg.near_plane = True, 0.6
    # densify in stage 1 only (the first time's many views), then the surroundings stand still
    cfg.static_iterations, cfg.densify.refine_stop, cfg.densify.max_gaussians = 3000, 3000, 40_000
    cfg.densify.reset_every = 1000  # (3DGS resets 5 times in its 15k steps of densification)
    cfg.stage2.static_outside_masks = cfg.stage2.freeze_surroundings = True
    return cfg


def tiny() -> TrainConfig:
    """A few iterations of everything: for tests and smoke runs."""
    cfg = cpu_fast()
    cfg.preset = "tiny"
    cfg.static_iterations, cfg.dynamic_iterations = 2, 2
    cfg.init_points = 200
    # densifying every step without a budget grows to 10^5 Gaussians on a real scene in a few steps
    cfg.densify = DensifyConfig(refine_start=0, refine_every=1, reset_every=0, max_gaussians=20_000)
    cfg.extrapolation.joint_laws = False  # (the tests that need them turn them on)
    return cfg


PRESETS = {"paper": paper, "cpu-fast": cpu_fast, "capture": capture, "tiny": tiny}
"""The named presets, each a function that builds its config (``--preset NAME``)."""


def make_config(preset: str = "cpu-fast", **overrides) -> TrainConfig:
    """A preset's config with fields set by name (``config.apply_overrides``: ``stage2.dt_frames``)."""
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    return apply_overrides(PRESETS[preset](), overrides)


def config_to_dict(cfg) -> dict:
    """A config as plain JSON data (paths as strings)."""

    def convert(v):
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, dict):
            return {k: convert(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [convert(x) for x in v]
        return v

    return convert(dataclasses.asdict(cfg))


def config_from_dict(cls, data: dict):
    """Rebuild a (nested) config dataclass from plain JSON data; unknown keys are an error."""
    hints = typing.get_type_hints(cls)
    kwargs = {}
    names = {f.name for f in dataclasses.fields(cls)}
    for key, value in data.items():
        if key not in names:
            raise ValueError(f"unknown config field {cls.__name__}.{key}")
        hint = hints[key]
        if dataclasses.is_dataclass(hint):
            value = config_from_dict(hint, value)
        elif hint is Path:
            value = Path(value)
        elif isinstance(value, list) and "tuple" in str(hint).lower():
            value = _as_tuple(value)
        kwargs[key] = value
    return cls(**kwargs)


def _as_tuple(value):
    return tuple(_as_tuple(v) for v in value) if isinstance(value, list) else value


def apply_overrides(cfg: TrainConfig, overrides: dict) -> TrainConfig:
    """A copy of ``cfg`` with fields set by their dotted names, as the command line spells them
    (``{"stage2.dt_frames": 3.0}`` for ``--stage2.dt-frames 3``); an unknown name is an error."""
    cfg = copy.deepcopy(cfg)
    for key, value in overrides.items():
        *sections, name = key.split(".")
        target = cfg
        for section in sections:
            target = getattr(target, section, None)
            if target is None or not dataclasses.is_dataclass(target):
                raise ValueError(f"unknown config section in {key!r}")
        if name not in {f.name for f in dataclasses.fields(target)}:
            raise ValueError(f"unknown config field {key!r}")
        setattr(target, name, value)
    return cfg
