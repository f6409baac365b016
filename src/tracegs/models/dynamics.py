"""The translation-rotation dynamics field f_trd(x, t) (Section 3.2, Eq. 3-6, Appendix).

N: particles (Gaussians), W: hidden width, E: encoded input channels.
An MLP maps the encoded 4-vector (x, y, z, t) to the per-particle dynamics parameters of
``physics/integrate.py``: equivalent centre velocity v_bar, angular velocity w, and (order >= 2)
accelerations a = a_raw |a_raw| / scale (element-wise, as the authors' code), (order 3) jerks scaled the same way.

Initialisation. The velocity outputs (and the explicit centre) start at exactly zero (zero weights and
biases), so a new field is "no motion" in velocity; their heads still receive gradients (hidden
features x upstream gradient) and after one optimiser step the gradient reaches every layer. The
acceleration outputs can NOT start at zero: d(a_raw |a_raw|)/d(a_raw) = 2 |a_raw| / scale vanishes
at a_raw = 0, so a zero-initialised acceleration head would receive no gradient, ever. They get a
small random init instead (``acceleration_init_std``), i.e. accelerations of order 1e-4 at start.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from tracegs.models import fused_mlp
from tracegs.models.encoding import (
    encoding_dim,
    linear_of_parts,
    positional_encoding,
    product_of_parts,
    time_column,
    time_rows,
)
from tracegs.physics.integrate import DynamicsParams, equivalent_from_center

ACTIVATIONS = {"silu": nn.SiLU, "relu": nn.ReLU}
ACCELERATIONS = ("acceleration", "angular_acceleration", "jerk", "angular_jerk")
"""The outputs scaled as a_raw |a_raw| / scale, last in ``output_slices``."""


@dataclass
class DynamicsConfig:
    """The dynamics field f_trd (defaults: the paper's Appendix)."""

    depth: int = 8
    """Hidden layers of the MLP (Appendix: 8 x 256)."""
    width: int = 256
    """Hidden width of the MLP."""
    num_frequencies: int = 6
    """Frequencies L of the encoding [u, sin(2^k u), cos(2^k u)] of the 4-vector (x, y, z, t)."""
    time_frequencies: int | None = None
    """Frequencies of the time channel when it should differ from the positions' (``num_frequencies``
    then applies to x, y, z only); None: one L for the whole 4-vector (the paper). Spatial frequencies
    let f_trd separate parts, and also let a spatially varying v_bar stand in for a rotation
    (docs/PHYSICS.md); time frequencies let velocities change within the span."""
    activation: str = "silu"
    """Hidden activation: "silu" (authors' code) or "relu" (the paper's Appendix)."""
    order: int = 2
    """1: velocities only (accelerations zero); 2: + constant accelerations (the paper);
    3: + jerk (accelerations evolve linearly)."""
    equivalent: bool = True
    """Learn the equivalent centre velocity/acceleration (Eq. 5). False: learn the centre P_c, its
    velocity and acceleration explicitly and convert (the "no equivalence" ablation)."""
    acceleration_scale: float = 10.0
    """a = a_raw * |a_raw| / acceleration_scale, element-wise, for accelerations and jerks."""
    acceleration_init_std: float = 1e-2
    """Std of the normal init of the raw-acceleration (and jerk) head weights; must be > 0 for them
    to learn (see the module docstring)."""

    detach_acceleration_features: bool = False
    """Compute the acceleration (and jerk) outputs from the MLP's features with their gradient stopped:
    a loss on the accelerations (``dynamic.acceleration_consistency``) then trains only their head and
    leaves the features, hence the velocities, to the photometric loss (measured: without the stop the
    consistency loss degrades the velocity fit; tests/models/test_fields.py)."""
    acceleration_depth: int = 0
    """0: the accelerations (and jerks) are read from the velocities' MLP by the shared head. > 0:
    they have their own MLP of this many hidden layers (width ``width``) on the same encoding, so that
    they can follow time as the velocities do while a loss on them cannot bend the velocities'
    features (docs/PHYSICS.md); ``detach_acceleration_features`` then applies to the rates the shared
    head still gives (``angular_accelerations_from_head``)."""
    angular_accelerations_from_head: bool = False
    """With ``acceleration_depth`` > 0: the own MLP gives the linear acceleration (and jerk) only, and
    the angular ones are read from the velocities' features by the shared head, as without it. The
    angular rates of a body that spins steadily are its w's slope in time, which an MLP of their own
    follows into the wiggles of the fitted w at the end of the training span (docs/PHYSICS.md)."""

    @classmethod
    def light(cls, **overrides) -> DynamicsConfig:
        """A lighter field than the paper's: L = 3, 6 x 128."""
        return cls(**{"depth": 6, "width": 128, "num_frequencies": 3, **overrides})

    def output_slices(self) -> dict[str, slice]:
        """Named slices of the head's raw outputs, in order."""
        names = ["velocity", "angular_velocity"]
        if not self.equivalent:
            names = ["center", "center_velocity", "angular_velocity"]
        if self.order >= 2:
            names += ["acceleration", "angular_acceleration"]
        if self.order >= 3:
            names += ["jerk", "angular_jerk"]
        return {name: slice(3 * i, 3 * i + 3) for i, name in enumerate(names)}


def scale_acceleration(raw: torch.Tensor, scale: float) -> torch.Tensor:
    """``raw * |raw| / scale`` (the authors' code): signed square, small near zero, large values reachable."""
    return raw * raw.abs() / scale


def hidden_layers(in_dim: int, depth: int, width: int, activation: str) -> nn.Sequential:
    """``depth`` x (Linear, activation), ``in_dim`` -> ``width``."""
    layers: list[nn.Module] = []
    for i in range(depth):
        layers += [nn.Linear(in_dim if i == 0 else width, width), ACTIVATIONS[activation]()]
    return nn.Sequential(*layers)


class DynamicsField(nn.Module):
    """f_trd: ``forward(x [N, 3], t) -> DynamicsParams`` (Eq. 6), in the dtype of ``x``."""

    def __init__(self, cfg: DynamicsConfig):
        super().__init__()
        if cfg.order not in (1, 2, 3):
            raise ValueError(f"order must be 1, 2 or 3, got {cfg.order}")
        if cfg.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {cfg.activation!r}")
        if cfg.acceleration_depth < 0:
            raise ValueError(f"acceleration_depth must be >= 0, got {cfg.acceleration_depth}")
        self.cfg = cfg
        self.slices = cfg.output_slices()
        in_dim = self.encode(torch.zeros(1, 3), 0.0).shape[-1]  # the encoding says its own width
        channel = torch.arange(in_dim) % 4  # the joint (x, y, z, t) encoding's channel of each column
        self.register_buffer("position_columns", torch.nonzero(channel != 3)[:, 0], persistent=False)
        self.register_buffer("time_columns", torch.nonzero(channel == 3)[:, 0], persistent=False)
        self.mlp = hidden_layers(in_dim, cfg.depth, cfg.width, cfg.activation)
        # which outputs the shared head gives, in ``slices`` order; with ``acceleration_depth`` the
        # rates (all, or the linear ones) come from an MLP of their own instead
        own = []
        if cfg.acceleration_depth > 0:
            angular = ("angular_acceleration", "angular_jerk") if cfg.angular_accelerations_from_head else ()
            own = [n for n in self.slices if n in ACCELERATIONS and n not in angular]
        self.head_names = [n for n in self.slices if n not in own]
        self.own_names = own
        head_rates = [n for n in self.head_names if n in ACCELERATIONS]  # the head's last rows
        self._head_rates_start = self.head_rows(head_rates[0]).start if head_rates else None
        self.head = nn.Linear(cfg.width, 3 * len(self.head_names))
        if own:
            self.acceleration_mlp = hidden_layers(in_dim, cfg.acceleration_depth, cfg.width, cfg.activation)
            self.acceleration_head = nn.Linear(cfg.width, 3 * len(own))
        self._init_head()

    @property
    def separate_accelerations(self) -> bool:
        """Whether the accelerations (and jerks; all, or the linear ones) have their own MLP
        (``acceleration_depth``)."""
        return bool(self.own_names)

    def head_rows(self, name: str) -> slice:
        """The rows of ``head`` (or, for a rate of the own MLP, of ``acceleration_head``) that give
        the named output."""
        names = self.head_names if name in self.head_names else self.own_names
        i = names.index(name)
        return slice(3 * i, 3 * i + 3)

    @torch.no_grad()
    def _init_head(self) -> None:
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        if self.separate_accelerations:
            nn.init.normal_(self.acceleration_head.weight, std=self.cfg.acceleration_init_std)
            nn.init.zeros_(self.acceleration_head.bias)
        for name in ACCELERATIONS:
            if name in self.head_names:
                nn.init.normal_(self.head.weight[self.head_rows(name)], std=self.cfg.acceleration_init_std)

    def encode(self, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """The encoded 4-vector (x, y, z, t) [N, E]: one L for all four channels, or the positions'
        and the time's own (``time_frequencies``)."""
        time = time_column(t, x)
        L = self.cfg.num_frequencies
        if self.cfg.time_frequencies is None:
            return positional_encoding(torch.cat([x, time], dim=-1), L)
        return torch.cat(
            [positional_encoding(x, L), positional_encoding(time, self.cfg.time_frequencies)], dim=-1
        )

    def _input_parts(self, x: torch.Tensor, t: float | torch.Tensor) -> list:
        """``encode(x, t)`` as (values, first-layer columns) pairs for ``linear_of_parts``: the
        positions' encoding [N, Ex] and the time's [1 or N, Et], wherever ``encode`` puts them."""
        L, time = self.cfg.num_frequencies, time_rows(t, x)
        if self.cfg.time_frequencies is None:  # one 4-vector encoding: time is every 4th channel
            return [
                (positional_encoding(x, L), self.position_columns),
                (positional_encoding(time, L), self.time_columns),
            ]
        ex = encoding_dim(3, L)
        return [
            (positional_encoding(x, L), slice(0, ex)),
            (positional_encoding(time, self.cfg.time_frequencies), slice(ex, None)),
        ]

    def outputs(
        self, x: torch.Tensor, t: float | torch.Tensor, rates: bool = True
    ) -> dict[str, torch.Tensor]:
        """The head's named outputs [N, 3] (``cfg.output_slices``; accelerations and jerks scaled), in
        the dtype of ``x``: for the non-equivalent variant the explicit centre P_c and its velocity,
        before ``forward`` converts them (Eq. 5). ``rates=False``: without the accelerations and jerks
        (and without the work that only they need).

        The MLP on ``encode(x, t)``, its first layer evaluated part by part (``linear_of_parts``: a
        time shared by all points enters as a bias)."""
        parts = self._input_parts(x, t)
        if fused_mlp.applies(x):
            return self._fused_outputs(parts, rates)
        raw, own = self._raw(parts, rates)
        named = {n: raw[:, self.head_rows(n)] for n in self.head_names if rates or n not in ACCELERATIONS}
        if own is not None:
            named |= {n: own[:, self.head_rows(n)] for n in self.own_names}
        out = {name: named[name].to(x.dtype) for name in self.slices if name in named}
        for name in ACCELERATIONS:
            if name in out:
                out[name] = scale_acceleration(out[name], self.cfg.acceleration_scale)
        return out

    def _raw(self, parts: list, rates: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        """The head's raw outputs [N, 3 k] and the own MLP's (None without it, or without ``rates``)."""
        own_hidden = None
        if rates and self.separate_accelerations:
            # both MLPs read the same encoding: their first layers run as one product, one activation
            first, own_first = self.mlp[0], self.acceleration_mlp[0]
            weight = torch.cat([first.weight, own_first.weight])
            bias = torch.cat([first.bias, own_first.bias])
            hidden = self.mlp[1](product_of_parts(weight, bias, parts))
            hidden, own_hidden = hidden.split((first.out_features, own_first.out_features), dim=-1)
        else:
            hidden = self.mlp[1](linear_of_parts(self.mlp[0], parts))
        features = self.mlp[2:](hidden)
        raw = self.head(features)
        start = self._head_rates_start
        if rates and start is not None and self.cfg.detach_acceleration_features:
            raw = torch.cat([raw[:, :start], self.head(features.detach())[:, start:]], dim=-1)
        own = None if own_hidden is None else self.acceleration_head(self.acceleration_mlp[2:](own_hidden))
        return raw, own

    def _fused_outputs(self, parts: list, rates: bool) -> dict[str, torch.Tensor]:
        """``outputs`` as native ops (``fused_mlp``): the MLP and its head as one, each named output
        its own tensor and the rates scaled inside it, the rates' stopped gradient
        (``detach_acceleration_features``) inside it too, and the own MLP with its head as another on
        the same encoding (two first-layer products, the same FLOPs as one stacked)."""

        named = {}
        for layers, names, stop_from, scaled_from in self.fused_chains(rates):
            outs = fused_mlp.fused_mlp_of_parts(
                parts,
                [layer.weight for layer in layers],
                [layer.bias for layer in layers],
                self.cfg.activation,
                stop_from=stop_from,
                groups=(3,) * len(names),
                scaled_from=scaled_from,
                scale=self.cfg.acceleration_scale,
            )
            named |= dict(zip(names, outs, strict=True))
        return {
            name: named[name]
            for name in self.slices
            if name in named and (rates or name not in ACCELERATIONS)
        }

    def fused_chains(
        self, rates: bool = True
    ) -> list[tuple[list[nn.Linear], list[str], int | None, int | None]]:
        """The fused op's calls of ``outputs``: per MLP its layers (the head last), the names of its
        output groups, the output column from which its input gets no gradient (``stop_from``:
        ``detach_acceleration_features``) and from which its outputs are rates scaled r |r| / scale
        (``scaled_from``; None: none). The own rates' MLP only with ``rates``."""

        def chain(mlp: nn.Sequential, head: nn.Linear, names: list[str], stop_from: int | None):
            scaled = [i for i, name in enumerate(names) if name in ACCELERATIONS]  # (the last ones)
            layers = [*[m for m in mlp if isinstance(m, nn.Linear)], head]
            return layers, names, stop_from, 3 * scaled[0] if scaled else None

        start = self._head_rates_start
        stop = rates and start is not None and self.cfg.detach_acceleration_features
        chains = [chain(self.mlp, self.head, self.head_names, start if stop else None)]
        if rates and self.separate_accelerations:
            chains.append(chain(self.acceleration_mlp, self.acceleration_head, self.own_names, None))
        return chains

    def forward(self, x: torch.Tensor, t: float | torch.Tensor, rates: bool = True) -> DynamicsParams:
        """Dynamics parameters of particles at positions ``x`` [N, 3] at time ``t`` (float or [N, 1]);
        with ``rates=False`` the velocities only (accelerations zero, as for order 1)."""
        return self.params(self.outputs(x, t, rates))

    def params(self, out: dict[str, torch.Tensor]) -> DynamicsParams:
        """``outputs`` as the integrator's parameters: zero accelerations for order 1, and the explicit
        centre's motion converted to the equivalent one (Eq. 5) for the non-equivalent variant."""
        zero = torch.zeros_like(out["angular_velocity"])
        acceleration = out.get("acceleration", zero)
        angular_acceleration = out.get("angular_acceleration", zero)
        if self.cfg.equivalent:
            return DynamicsParams(
                out["velocity"],
                out["angular_velocity"],
                acceleration,
                angular_acceleration,
                out.get("jerk"),
                out.get("angular_jerk"),
            )
        return equivalent_from_center(
            out["center"],
            out["center_velocity"],
            acceleration,
            out["angular_velocity"],
            angular_acceleration,
            out.get("jerk"),
            out.get("angular_jerk"),
        )
