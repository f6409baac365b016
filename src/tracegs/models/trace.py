"""TRACE: canonical Gaussians + auxiliary deformation field f_defo + translation-rotation dynamics f_trd.

This module says how the Gaussians at a time t are made in training (Section 3.3: deform to t',
transport t' -> t with the learned physics, Alg. 1). What happens after training (the handover, what
holds still, free bodies; rendering any time) is ``tracegs.extrapolate``. The DefGS baseline is the
same model without f_trd; "static" is plain 3DGS.
N: Gaussians.
"""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from ..physics.free_body import median_spacing
from ..physics.integrate import acceleration_consistency, integrate_rows, integrate_states, params_in_world
from ..render import rasterize
from . import fields_step
from .colour import CameraColour
from .config import ModelConfig
from .deformation import deform_rows, make_deformation_field
from .dynamics import DynamicsField


class TraceModel(nn.Module):
    """Gaussians (``self.gaussians``), and the fields the method needs (``deformation``, ``dynamics``)."""

    def __init__(
        self,
        settings: ModelConfig,
        gaussians: nn.ParameterDict,
        aabb: torch.Tensor,
        frame_interval: float,
        camera_ids: list[int] | None = None,
    ):
        """``settings``: what the model is made of (``TrainConfig.model_config``); ``camera_ids``: the
        training cameras whose colours ``settings.camera_colour`` learns (a trained run's are read from
        its checkpoint)."""
        super().__init__()
        self.method = settings.method
        """``trace``, ``defgs`` or ``static``."""
        self.stage2 = settings.stage2
        """How stage 2 trains the fields (``Stage2Config``; its ``integrator`` also extrapolates)."""
        self.sh_degree = settings.sh_degree
        """The SH degree of the trained colours, that every image of the run is drawn with."""
        self.backend = settings.backend
        """The rasteriser backend every image is drawn with (``render.rasterize``'s)."""
        self.bf16 = settings.bf16
        """bf16 autocast of the fields on CPU; ``run.fields_in_bf16`` (loading and training) keeps it only on
        CPUs with hardware bf16."""
        self.gaussians = gaussians
        self.register_buffer("aabb", aabb.clone().float())
        self.register_buffer("frame_interval", torch.tensor(float(frame_interval)))
        # the frame the fields see positions in (``set_field_frame``); the world's until set
        self.register_buffer("field_center", torch.zeros(3))
        self.register_buffer("field_scale", torch.ones(()))
        self.register_buffer("near_plane", torch.tensor(0.01))  # world units (``set_near_plane``)
        self._near = 0.01
        self._frame_scale: float | None = None  # the scale as a number; None: the world's frame
        self.register_load_state_dict_pre_hook(_default_field_frame)
        self.register_load_state_dict_post_hook(_sync_frame_after_load)
        method = settings.method
        uses_deformation = method == "defgs" or (method == "trace" and settings.stage2.use_deformation)
        self.deformation = make_deformation_field(settings.deformation, aabb) if uses_deformation else None
        self.dynamics = DynamicsField(settings.dynamics) if method == "trace" else None
        self.camera_colour = CameraColour(camera_ids or []) if settings.camera_colour else None
        self.static_mask: torch.Tensor | None = None
        """[N] bool: Gaussians marked static during training (``stage2.skip_static``), kept at their
        canonical geometry at every time and skipped by the fields; None: the fields move them all."""
        self._moving: torch.Tensor | None = None  # indices of the others

    # ----- the fields' frame ----------------------------------------------------------------------
    def set_field_frame(self, center: torch.Tensor, scale: float) -> None:
        """The fields see positions as ``(x - center) / scale`` and their displacements and
        velocities are scaled back (``field_frame`` in ``train/scene_frame.py`` chooses it). Their
        positional encodings (``sin(2^k pi x)``) and output sizes are made for scenes within a few
        units of the origin; a capture in other units or far from the origin is brought there."""
        self.field_center.copy_(torch.as_tensor(center, dtype=torch.float32))
        self.field_scale.fill_(float(scale))
        self._sync_frame()

    def set_near_plane(self, near: float) -> None:
        """Gaussians nearer a camera than ``near`` (world units, along its axis) are not drawn."""
        self.near_plane.fill_(float(near))
        self._sync_frame()

    def _sync_frame(self) -> None:
        self._near = float(self.near_plane)
        identity = bool((self.field_center == 0).all()) and float(self.field_scale) == 1.0
        self._frame_scale = None if identity else float(self.field_scale)

    @property
    def fields_see_world(self) -> bool:
        """Whether the fields see world coordinates (the frame is the identity)."""
        return self._frame_scale is None

    def to_field_frame(self, x: torch.Tensor) -> torch.Tensor:
        """World positions [N, 3] as the fields see them."""
        return x if self._frame_scale is None else (x - self.field_center) / self._frame_scale

    # ----- fields -----------------------------------------------------------------------------
    def field_parameters(self) -> list[nn.Parameter]:
        return [p for m in (self.deformation, self.dynamics) if m is not None for p in m.parameters()]

    def field_parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """The fields' parameters by optimiser group: ``"grid"`` (HexPlane planes) and ``"fields"`` (the rest)."""
        grid = getattr(self.deformation, "grid", None)
        grid_ids = {id(p) for p in grid.parameters()} if grid is not None else set()
        params = self.field_parameters()
        return {
            "fields": [p for p in params if id(p) not in grid_ids],
            "grid": [p for p in params if id(p) in grid_ids],
        }

    def regularization_losses(self) -> dict[str, torch.Tensor]:
        """Named, weighted regularisers of the fields (the HexPlane's TV and time terms), for the
        dynamic stage's loss; empty for fields without any."""
        field = self.deformation
        return field.regularization_losses() if hasattr(field, "regularization_losses") else {}

    def begin_dynamic_stage(self) -> None:
        """Once, when stage 2 starts: fields with a spatial box (the HexPlane) fit it to the canonical
        Gaussians of stage 1."""
        if hasattr(self.deformation, "fit_bounds"):
            self.deformation.fit_bounds(self.to_field_frame(self.gaussians["means"].detach()))

    @property
    def fields_bf16(self) -> bool:
        """Whether the fields run under bf16 autocast: ``bf16`` set and the model on the CPU."""
        return bool(self.bf16) and self.aabb.device.type == "cpu"

    def autocast(self):
        """bf16 autocast for the fields on CPU when configured (AMX or AVX512-BF16: faster products)."""
        if self.fields_bf16:
            return torch.autocast("cpu", dtype=torch.bfloat16)
        return contextlib.nullcontext()

    def deform(self, t: float) -> dict[str, torch.Tensor]:
        """Eq. 2: canonical Gaussians moved to time t by f_defo (identity if there is no f_defo)."""
        return self.deform_many([t])[0]

    def deform_many(self, times: list[float]) -> list[dict[str, torch.Tensor]]:
        """:meth:`deform` at several times in one batched pass of the field (larger GEMMs are faster)."""
        g, names = self.gaussians, ("means", "quats", "scales")
        if self.deformation is None:
            return [{name: g[name] for name in names} for _ in times]
        rows = self._moving_rows()
        canonical = [g[name] for name in names]
        x0 = canonical[0].detach() if self.deformation.cfg.detach_input else canonical[0]
        x0 = self.to_field_frame(x0 if rows is None else x0[rows])
        n = x0.shape[0]
        if len(times) == 1:  # one time for all points: the field takes it as a bias (``linear_of_parts``)
            x, t = x0, times[0]
        else:
            x = x0.repeat(len(times), 1)
            t = torch.tensor(times, dtype=x.dtype, device=x.device).repeat_interleave(n)[:, None]
        with self.autocast():
            dx, dq, dlog_s = self.deformation(x, t)
        if self._frame_scale is not None:
            dx = dx.float() * self._frame_scale
        states = []
        for k in range(len(times)):  # (the static Gaussians keep their canonical rows)
            outputs = (dx, dq, dlog_s)  # (one time: all rows, without slices)
            if len(times) > 1:
                outputs = tuple(out[k * n : (k + 1) * n] for out in outputs)
            moved = deform_rows(canonical, rows, *[out.float() for out in outputs])
            states.append(dict(zip(names, moved, strict=True)))
        return states

    def query_dynamics(self, means: torch.Tensor, t: float, rates: bool = True):
        """Eq. 6: the learned physical parameters of every particle at time t (float32); with
        ``rates=False`` the velocities only (``DynamicsField.forward``)."""
        with self.autocast():
            params = self.dynamics(self.to_field_frame(means), t, rates)
        params = type(params)(*[None if p is None else p.float() for p in params])
        if self._frame_scale is None:
            return params
        return params_in_world(params, self.field_center, self._frame_scale)

    # ----- Gaussians that stand still (``stage2.skip_static``) ---------------------------------------
    @torch.no_grad()
    def mark_static(self, threshold: float, t_max: float, samples: int = 16, margin: float = 0.0) -> float:
        """Mark the Gaussians whose f_defo displacement stays below ``threshold`` (scene units) at
        ``samples + 1`` times in [0, t_max] as static, except those within ``margin`` times the median
        nearest-neighbour spacing of a Gaussian that moves; returns their fraction. Without f_defo
        nothing is marked (what moves is not known).

        The margin keeps a moving part whole: next to a hinge a part barely moves, and where f_defo has
        not yet learned all of a part when the marking is made (a seat that starts from rest), its
        slow patch would be frozen for good while the rest turns."""
        self.set_static_mask(None)
        if self.deformation is None:
            return 0.0
        still = self.max_displacement(t_max, samples) < threshold
        if margin > 0 and bool(still.any()) and not bool(still.all()):
            still &= ~near_points(self.gaussians["means"].detach(), ~still, margin)
        self.set_static_mask(still)
        return float(self.static_mask.float().mean())

    def set_static_mask(self, mask: torch.Tensor | None) -> None:
        """Set (or clear, with None) the [N] bool mask of static Gaussians."""
        if mask is not None:
            n = self.gaussians["means"].shape[0]
            if mask.shape != (n,) or mask.dtype != torch.bool:
                raise ValueError(
                    f"static mask: expected a bool tensor of shape ({n},), got {tuple(mask.shape)}"
                )
            mask = mask.to(self.aabb.device)
        self.static_mask = mask
        self._moving = None if mask is None else torch.nonzero(~mask).squeeze(1)

    @property
    def moving_rows(self) -> torch.Tensor | None:
        """Indices of the Gaussians not held static (None: no static mask)."""
        return self._moving_rows()

    def _moving_rows(self) -> torch.Tensor | None:
        """Indices of the Gaussians the fields move, or None when they move all of them."""
        if self._moving is not None and self.static_mask.shape[0] != self.gaussians["means"].shape[0]:
            raise RuntimeError(
                "the set of Gaussians changed after they were marked static (densification must have "
                "stopped before stage2.skip_static marks them)"
            )
        return self._moving

    # ----- the Gaussians of a training step -----------------------------------------------------
    def training_state(
        self, t_prime: float, t: float, t_check: float | None = None
    ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        """Gaussians for rendering frame ``t`` in stage 2 (the paper, Section 3.3), and the step's
        weighted auxiliary losses by name (``acceleration``, when ``stage2.acceleration_consistency``
        is set).

        TRACE: deform to t', query f_trd at (x_t', t'), integrate t' -> t, and pass f_defo(t')'s
        gradient straight through to the rendered position (the physics starts from a detached x_t').
        DefGS: f_defo(t) alone. ``t_check``: where the acceleration consistency
        reads f_trd's velocities again (default ``t``; ``Stage2Config.consistency_frames``). Where
        ``fields_step.applies`` (the CPU presets' fields), the same computation runs as one autograd
        node (``models/fields_step.py``, the same bits).
        """
        stage = self.stage2
        if self.dynamics is None:
            return self.deform(t), {}
        if fields_step.applies(self, t_prime, t):  # (the same step as one autograd node)
            return fields_step.training_state(self, t_prime, t, t_check)
        if self.deformation is None:  # ablation "no f_defo": dynamics carry the canonical Gaussians from 0
            t_prime = 0.0
        straight_through = self.deformation is not None
        start = self.deform(t_prime)
        x_start = start["means"].detach() if straight_through else start["means"]
        query_time = t_prime if stage.physics_derivation else t
        rows = self._moving_rows()  # f_trd moves these; the static Gaussians stay where they are
        x_run = x_start if rows is None else x_start[rows]
        params = self.query_dynamics(x_run, query_time)
        means, quats, moved = integrate_rows(
            start["means"],
            start["quats"],
            rows,
            params,
            t - t_prime,
            self.dt_max,
            stage.integrator,
            straight_through,
        )
        losses = {}
        share = 1.0 if rows is None else rows.numel() / x_start.shape[0]  # a mean over all Gaussians
        learns_accelerations = self.dynamics.cfg.order >= 2 and stage.physics_derivation
        # (not when every Gaussian is marked static: a mean over no particles is NaN)
        t_check = t if t_check is None else t_check
        if stage.acceleration_consistency > 0 and learns_accelerations and t_check != t_prime and len(x_run):
            with torch.no_grad():  # f_trd once more at t_check, where x_t' is carried there
                if t_check != t:
                    span = t_check - t_prime
                    x_check = integrate_states(
                        x_run, None, params, span, self.dt_max, method=stage.integrator
                    )[0]
                else:
                    x_check = moved
                later = self.query_dynamics(x_check, t_check, rates=False)  # it reads velocities
            gap = acceleration_consistency(params, later, t_check - t_prime)  # the static ones' gap is zero
            losses["acceleration"] = stage.acceleration_consistency * share * gap
        return {"means": means, "quats": quats, "scales": start["scales"]}, losses

    # ----- f_defo over the training span ----------------------------------------------------
    @torch.no_grad()
    def max_displacement(self, t_max: float, samples: int = 8) -> torch.Tensor:
        """[N] the largest f_defo displacement of each Gaussian over ``samples + 1`` times in [0, t_max]."""
        x0 = self.gaussians["means"]
        most = torch.zeros(x0.shape[0], device=x0.device)
        for k in range(samples + 1):
            most = torch.maximum(most, (self.deform(t_max * k / samples)["means"] - x0).norm(dim=-1))
        return most

    @property
    def dt_max(self) -> float:
        """Longest single integration step: one frame interval of the training data."""
        return float(self.frame_interval)

    # ----- rendering --------------------------------------------------------------------------
    def colour(self, image: torch.Tensor, camera_id: int | None) -> torch.Tensor:
        """A rendered ``image`` [H, W, 3] in the colours of training camera ``camera_id``
        (``camera_colour``); unchanged without it, or for a camera that was not trained."""
        return image if self.camera_colour is None else self.camera_colour(image, camera_id)

    def render(
        self,
        state: dict[str, torch.Tensor],
        camera,
        sh_degree: int,
        background: torch.Tensor | None,
        rows=None,
        colors: torch.Tensor | None = None,
    ):
        """Rasterise Gaussians whose geometry is ``state`` (means, quats, log-scales) from ``camera``;
        ``rows``: only those Gaussians (indices); ``colors``: [N, 3] drawn instead of their SH colours
        (e.g. segment labels; ``sh_degree`` then unused). Every image of the run goes through here,
        so all are drawn with its near plane and backend."""
        g = self.gaussians
        sh = torch.cat([g["sh0"], g["shN"]], dim=1) if colors is None else colors
        opacities = torch.sigmoid(g["opacities"])
        if rows is not None:
            state = {k: state[k][rows] for k in ("means", "quats", "scales")}
            sh, opacities = sh[rows], opacities[rows]
        return rasterize(
            state["means"],
            state["quats"],
            torch.exp(state["scales"]),
            opacities,
            sh,
            camera.viewmat,
            camera.K,
            camera.width,
            camera.height,
            sh_degree=sh_degree if colors is None else None,
            background=background,
            near_plane=self._near,
            backend=self.backend,
        )


def _default_field_frame(module, state_dict, prefix, *_) -> None:
    """Checkpoints written before the fields had a frame of their own: the world's."""
    state_dict.setdefault(prefix + "field_center", torch.zeros(3))
    state_dict.setdefault(prefix + "field_scale", torch.ones(()))
    state_dict.setdefault(prefix + "near_plane", torch.tensor(0.01))  # (the rasteriser's default, gsplat's)


def _sync_frame_after_load(module, _incompatible_keys) -> None:
    module._sync_frame()


def near_points(means: torch.Tensor, seeds: torch.Tensor, margin: float) -> torch.Tensor:
    """[N] bool: the points ``means`` [N, 3] within ``margin`` times their median nearest-neighbour
    spacing (``physics.free_body.median_spacing``) of a point of ``seeds`` [N] bool."""
    from scipy.spatial import cKDTree

    x = means.float().cpu().numpy()
    distance = cKDTree(x[seeds.cpu().numpy()]).query(x)[0]
    return torch.as_tensor(distance <= margin * median_spacing(x), device=means.device)
