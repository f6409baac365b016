"""Native CPU backend: C++/OpenMP projection and tile rasteriser with explicit backward kernels.

The extension (``csrc/raster_cpu.cpp``) is JIT-compiled on first use (``tracegs.cpp``). If it cannot
be built, :func:`load_extension` returns ``None`` and warns once, and ``rasterize(backend="auto")``
falls back to the reference.

Two autograd functions mirror gsplat's split: projection (``means, quats, scales -> means2d, conics,
depths``) and blending (``means2d, conics, colors, opacities, depths -> images``). The split keeps
``means2d`` a real node of the graph, so its ``.grad`` is the screen-space gradient that 3DGS
densification reads. Everything runs in float32; the thread count is ``torch.get_num_threads()``.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..cpp import EXTENSIONS
from .reference import Projection
from .sh import check_sh_coeffs

EXTENSION = EXTENSIONS["tracegs_raster_cpu"]


def load_extension():
    """Build (first call) or load the C++ extension; ``None`` (with one warning) if that fails."""
    return EXTENSION.load()


def is_available() -> bool:
    """Whether the native backend can be used (builds the extension on first call)."""
    return load_extension() is not None


def _f32(t: Tensor) -> Tensor:
    return t.detach().to(torch.float32).contiguous()


class _ProjectFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d):
        ext = load_extension()
        nt = torch.get_num_threads()
        means2d, conics, depths, radii, extents = ext.project_forward(
            means, quats, scales, opacities, viewmat, K, width, height, near, far, eps2d, nt
        )
        ctx.save_for_backward(means, quats, scales, viewmat, K, radii, conics)
        ctx.cfg = (width, height, eps2d)
        ctx.mark_non_differentiable(radii, extents)
        return means2d, conics, depths, radii, extents

    @staticmethod
    def backward(ctx, v_means2d, v_conics, v_depths, _v_radii, _v_extents):
        means, quats, scales, viewmat, K, radii, conics = ctx.saved_tensors
        width, height, eps2d = ctx.cfg
        v_means, v_quats, v_scales = load_extension().project_backward(
            means,
            quats,
            scales,
            viewmat,
            K,
            radii,
            conics,
            v_means2d.contiguous(),
            v_conics.contiguous(),
            v_depths.contiguous(),
            width,
            height,
            eps2d,
            torch.get_num_threads(),
        )
        return v_means, v_quats, v_scales, None, None, None, None, None, None, None, None


class _RasterizeFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, colors, opacities, depths, extents, radii, width, height):
        ext = load_extension()
        nt = torch.get_num_threads()
        color, alpha, depth, final_t, last, tile_off, flat_ids, gauss_off, isect_pos = ext.raster_forward(
            means2d, conics, colors, opacities, depths, extents, radii, width, height, nt
        )
        ctx.save_for_backward(
            means2d,
            conics,
            colors,
            opacities,
            depths,
            extents,
            final_t,
            last,
            tile_off,
            flat_ids,
            gauss_off,
            isect_pos,
        )
        ctx.cfg = (width, height)
        return color, alpha, depth

    @staticmethod
    def backward(ctx, v_color, v_alpha, v_depth):
        width, height = ctx.cfg
        grads = load_extension().raster_backward(
            *ctx.saved_tensors,
            v_color.contiguous(),
            v_alpha.contiguous(),
            v_depth.contiguous(),
            width,
            height,
            torch.get_num_threads(),
        )
        v_means2d, v_conics, v_colors, v_opacities, v_depths = grads
        return v_means2d, v_conics, v_colors, v_opacities, v_depths, None, None, None, None


class _SHFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, coeffs, viewmat, degree):
        ctx.save_for_backward(means, coeffs, viewmat)
        ctx.degree = degree
        return load_extension().sh_forward(means, coeffs, viewmat, degree, torch.get_num_threads())

    @staticmethod
    def backward(ctx, v_colors):
        means, coeffs, viewmat = ctx.saved_tensors
        v_means, v_coeffs = load_extension().sh_backward(
            means, coeffs, viewmat, ctx.degree, v_colors.contiguous(), torch.get_num_threads()
        )
        return v_means, v_coeffs, None, None


def sh_colors_native(means: Tensor, coeffs: Tensor, viewmat: Tensor, degree: int) -> Tensor:
    """C++ version of :func:`tracegs.render.sh.eval_sh_colors` (float32): [N, 3] colours of means
    [N, 3] with SH coefficients [N, K, 3] seen from the camera of ``viewmat`` [4, 4]."""
    check_sh_coeffs(coeffs, degree)
    f = torch.float32
    return _SHFunction.apply(means.to(f).contiguous(), coeffs.to(f).contiguous(), _f32(viewmat), int(degree))


def project_native(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """C++ version of :func:`tracegs.render.reference.project_gaussians` (float32)."""
    f = torch.float32
    means2d, conics, depths, radii, extents = _ProjectFunction.apply(
        means.to(f).contiguous(),
        quats.to(f).contiguous(),
        scales.to(f).contiguous(),
        _f32(opacities),
        _f32(viewmat),
        _f32(K),
        int(width),
        int(height),
        float(near_plane),
        float(far_plane),
        float(eps2d),
    )
    return Projection(means2d=means2d, conics=conics, depths=depths, radii=radii, extents=extents)


def rasterize_native(
    means2d: Tensor,  # [N, 2]
    conics: Tensor,  # [N, 3]
    colors: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    depths: Tensor,  # [N]
    extents: Tensor,  # [N, 2]
    radii: Tensor,  # [N]
    width: int,
    height: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """C++ version of :func:`tracegs.render.reference.rasterize_reference` (float32)."""
    f = torch.float32
    return _RasterizeFunction.apply(
        means2d.to(f).contiguous(),
        conics.to(f).contiguous(),
        colors.to(f).contiguous(),
        opacities.to(f).contiguous(),
        depths.to(f).contiguous(),
        _f32(extents),
        radii.to(torch.int32).contiguous(),
        int(width),
        int(height),
    )
