"""HexPlane feature grid of 4DGS (K-Planes style), the encoder of the TRACE_4dgs deformation field.

N: points, C: channels per plane, S: scales, H/W: plane resolutions.
A 4D point (x, y, z, t) is projected onto six axis-aligned planes (xy, xz, yz, xt, yt, zt); each plane
is sampled bilinearly, the six features are multiplied together (K-Planes' product: time planes start
at 1, so a new grid is static), and the products of all scales are concatenated [N, S C].
The decoder and the zero-initialised heads live in ``models/deformation.py`` (as in 4DGS, where the
grid and the deformation network are separate modules).

On the CPU the sampling, its backward and the planes' total variation run in a small C++/OpenMP
extension (``csrc/hexplane_cpu.cpp``, built on first use like the rasteriser) over channels-last
planes: torch's ``grid_sample`` backward is single-threaded on the CPU and made TRACE_4dgs's step
twice TRACE's. Elsewhere (CUDA), or if the extension cannot be built, ``grid_sample`` computes the
same function.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from ..cpp import EXTENSIONS

PLANES = tuple(itertools.combinations(range(4), 2))  # (0,1) xy (0,2) xz (0,3) xt (1,2) yz (1,3) yt (2,3) zt
# plane (i, j) is read with coordinate i along its width and j along its height (grid_sample's order)
_AXES = [axis for pair in PLANES for axis in pair]

EXTENSION = EXTENSIONS["tracegs_hexplane_cpu"]


@dataclass
class HexPlaneConfig:
    """The HexPlane grid and its decoder (defaults: 4DGS's D-NeRF setting)."""

    spatial_resolution: int = 64
    """Cells per spatial axis at scale 1 (4DGS: 64)."""
    time_resolution: int = 25
    """Cells along time (4DGS: 25 for the D-NeRF scenes); not multiplied by the scales."""
    multires: tuple[int, ...] = (1, 2)
    """Spatial resolution multipliers, one set of six planes per entry (4DGS: (1, 2))."""
    feature_dim: int = 32
    """Channels C of every plane (4DGS: 32 for synthetic scenes)."""
    aabb: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (-1.5, -1.5, -1.5),
        (1.5, 1.5, 1.5),
    )
    """Scene box (min, max) mapped to [-1, 1]; points outside are clamped. Usually replaced by the
    scene's bounds through the constructor's ``aabb`` argument."""
    time_range: tuple[float, float] = (0.0, 1.0)
    """Times mapped to [-1, 1] along the time axis of the planes."""
    init_range: tuple[float, float] = (0.1, 0.5)
    """Uniform initialisation of the spatial planes (4DGS / K-Planes)."""
    decoder_width: int = 64
    """Hidden width W of the decoder MLP (4DGS: net_width 64)."""
    decoder_depth: int = 2
    """Hidden layers of the decoder (feature -> W, then W -> W), each followed by a ReLU."""
    plane_tv_weight: float = 1e-4
    """Weight of the total variation of all planes in ``regularization_losses`` (4DGS: 1e-4)."""
    time_smoothness_weight: float = 1e-2
    """Weight of the second difference along time of the time planes (4DGS: 1e-2)."""
    time_l1_weight: float = 1e-4
    """Weight of |1 - time planes| (pulls towards a static scene; 4DGS: 1e-4)."""


def normalize_aabb(x: torch.Tensor, aabb: torch.Tensor) -> torch.Tensor:
    """Points [N, 3] mapped from the box ``aabb`` [2, 3] to [-1, 1]^3, clamped."""
    return ((x - aabb[0]) * (2 / (aabb[1] - aabb[0])) - 1).clamp(-1, 1)


def sample_plane(plane: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """Bilinear features [N, C] of ``plane`` [1, C, H, W] at ``coords`` [N, 2] in [-1, 1] (W, H order)."""
    grid = coords.to(plane.dtype)[None, None]  # [1, 1, N, 2]
    return F.grid_sample(plane, grid, mode="bilinear", padding_mode="border", align_corners=True)[0, :, 0].T


def _table(plane: torch.Tensor) -> torch.Tensor:
    """A plane [1, C, H, W] as the kernels' table [H, W, C] (a view of a channels-last plane)."""
    return plane[0].permute(1, 2, 0).contiguous()


def _untable(table_grad: torch.Tensor) -> torch.Tensor:
    return table_grad.permute(2, 0, 1)[None]


class _ProductSample(torch.autograd.Function):
    """The product of the bilinear samples of planes at ``coords`` [N, 4] (native kernels)."""

    @staticmethod
    def forward(ctx, coords, *planes):
        tables = [_table(plane) for plane in planes]
        out, samples = EXTENSION.module.hexplane_forward(tables, coords, _AXES, torch.get_num_threads())
        ctx.save_for_backward(coords, samples, *tables)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        coords, samples, *tables = ctx.saved_tensors
        wants_coords = ctx.needs_input_grad[0]
        grads = EXTENSION.module.hexplane_backward(
            tables,
            coords,
            _AXES,
            samples,
            grad_out.float().contiguous(),
            wants_coords,
            torch.get_num_threads(),
        )
        coords_grad = grads.pop() if wants_coords else None
        return coords_grad, *(_untable(g) for g in grads)


class _PlaneTV(torch.autograd.Function):
    """``scale * plane_tv`` with its gradient computed in the same pass (native kernel)."""

    @staticmethod
    def forward(ctx, plane, scale):
        loss, grad = EXTENSION.module.plane_tv(_table(plane), scale, torch.get_num_threads())
        ctx.save_for_backward(grad)
        return loss

    @staticmethod
    def backward(ctx, grad_loss):
        (grad,) = ctx.saved_tensors
        # a weighted term of a summed loss gets 1: spare a pass over the plane
        return _untable(grad if float(grad_loss) == 1.0 else grad * grad_loss), None


def _native(plane: torch.Tensor) -> bool:
    """Whether the native kernels serve this plane (float32 on the CPU, extension built)."""
    return plane.device.type == "cpu" and plane.dtype == torch.float32 and EXTENSION.load() is not None


def product_of_samples(planes, coords: torch.Tensor) -> torch.Tensor:
    """prod_k bilinear(planes[k], coords[:, PLANES[k]]): [N, C] features of one scale's six planes."""
    if _native(planes[0]):
        return _ProductSample.apply(coords.float().contiguous(), *planes)
    product = 1.0
    for (i, j), plane in zip(PLANES, planes, strict=True):
        product = product * sample_plane(plane, coords[:, [i, j]])
    return product


def plane_tv(plane: torch.Tensor, scale: float = 1.0) -> torch.Tensor:
    """``scale`` x total variation (mean squared first differences along H and W) of ``plane`` [1, C, H, W]."""
    if _native(plane):
        return _PlaneTV.apply(plane, float(scale))
    return scale * plane_tv_reference(plane)


def plane_tv_reference(plane: torch.Tensor) -> torch.Tensor:
    """``plane_tv`` in PyTorch operations (the definition; CUDA and the fallback)."""
    dh = (plane[..., 1:, :] - plane[..., :-1, :]).square().mean()
    dw = (plane[..., :, 1:] - plane[..., :, :-1]).square().mean()
    return 2 * (dh + dw)


def plane_time_smoothness(plane: torch.Tensor) -> torch.Tensor:
    """Mean squared second difference along H (time) of a time plane [1, C, T, W]."""
    first = plane[..., 1:, :] - plane[..., :-1, :]
    return (first[..., 1:, :] - first[..., :-1, :]).square().mean()


class HexPlane(nn.Module):
    """Multi-scale HexPlane grid: ``forward(x [N, 3], t [N, 1]) -> features [N, S C]``."""

    def __init__(self, cfg: HexPlaneConfig, aabb: torch.Tensor | None = None):
        super().__init__()
        self.cfg = cfg
        self.register_buffer("aabb", torch.as_tensor(cfg.aabb if aabb is None else aabb, dtype=torch.float32))
        self.register_buffer("time_range", torch.tensor(cfg.time_range, dtype=torch.float32))
        self.scales = nn.ModuleList()
        for multiplier in cfg.multires:
            resolution = [cfg.spatial_resolution * multiplier] * 3 + [cfg.time_resolution]
            planes = nn.ParameterList()
            for i, j in PLANES:
                # grid_sample reads coords (u, v) as (W, H): plane (i, j) is [1, C, res_j, res_i]
                plane = torch.empty(1, cfg.feature_dim, resolution[j], resolution[i])
                if j == 3:
                    nn.init.ones_(plane)
                else:
                    nn.init.uniform_(plane, *cfg.init_range)
                # channels last: a cell's C features are contiguous for the native kernels
                planes.append(nn.Parameter(plane.contiguous(memory_format=torch.channels_last)))
            self.scales.append(planes)

    @property
    def out_dim(self) -> int:
        return self.cfg.feature_dim * len(self.cfg.multires)

    def set_aabb(self, aabb: torch.Tensor) -> None:
        """Replace the scene box [2, 3] (e.g. by the bounds of the canonical Gaussians)."""
        self.aabb.copy_(torch.as_tensor(aabb, dtype=self.aabb.dtype))

    def fit_bounds(self, points: torch.Tensor, quantile: float = 0.002, margin: float = 0.05) -> None:
        """Box the grid around ``points`` [N, 3] (the canonical Gaussians when stage 2 starts).

        Points outside the box are clamped onto its faces and share their features, so the box must
        hold the whole scene, not only the moving object: with the object's box, static background
        beyond it would read the features of the object's edge and move with it. The box spans the
        ``quantile`` .. 1 - ``quantile`` range per axis (a few far floaters do not stretch the cells),
        widened by ``margin`` of its size on every side, and always contains the current box."""
        points = points.detach().float()
        lo = torch.quantile(points, quantile, dim=0)
        hi = torch.quantile(points, 1 - quantile, dim=0)
        pad = margin * (hi - lo).clamp_min(1e-6)
        aabb = self.aabb.float()
        self.set_aabb(torch.stack([torch.minimum(lo - pad, aabb[0]), torch.maximum(hi + pad, aabb[1])]))

    def forward(self, x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        lo, hi = self.time_range[0], self.time_range[1]
        t = ((t - lo) * (2 / (hi - lo)) - 1).clamp(-1, 1)
        u = torch.cat([normalize_aabb(x, self.aabb.to(x.dtype)), t.to(x.dtype)], dim=-1)  # [N, 4]
        return torch.cat([product_of_samples(list(planes), u) for planes in self.scales], dim=-1)

    def tv_loss(self, weight: float = 1.0) -> torch.Tensor:
        """``weight`` x total variation of every plane (4DGS's ``plane_tv``), averaged over the scales."""
        scale = weight / len(self.scales)
        return sum(plane_tv(p, scale) for planes in self.scales for p in planes)

    def time_planes(self) -> list[nn.Parameter]:
        """The xt, yt, zt planes of every scale."""
        return [
            plane for planes in self.scales for (_, j), plane in zip(PLANES, planes, strict=True) if j == 3
        ]

    def time_smoothness_loss(self) -> torch.Tensor:
        """Second-difference smoothness along time of the time planes, averaged over the scales."""
        return sum(plane_time_smoothness(p) for p in self.time_planes()) / len(self.scales)

    def time_l1_loss(self) -> torch.Tensor:
        """Mean |1 - time plane|, averaged over the scales: zero for a static grid."""
        return sum((1 - p).abs().mean() for p in self.time_planes()) / len(self.scales)

    def regularization_losses(self) -> dict[str, torch.Tensor]:
        """Named, weighted regularisers for the trainer to sum and log."""
        return {
            "plane_tv": self.tv_loss(self.cfg.plane_tv_weight),
            "time_smoothness": self.cfg.time_smoothness_weight * self.time_smoothness_loss(),
            "time_l1": self.cfg.time_l1_weight * self.time_l1_loss(),
        }
