"""``rasterize()``: the one entry point for rendering 3D Gaussians, whatever the backend.

Backends (``backend=``):

* ``"gsplat"``    - ``gsplat.rasterization`` on CUDA tensors.
* ``"native"``    - C++/OpenMP CPU kernels with explicit backward passes (:mod:`.native`).
* ``"reference"`` - pure PyTorch, tile-based, used as ground truth in the tests (:mod:`.reference`).
* ``"auto"``      - gsplat for CUDA tensors when it imports, else native when the extension
  builds (CPU tensors), else reference.

The CPU backends share SH evaluation (:mod:`.sh`), the depth normalisation and the background
compositing below, so they differ only in projection and blending.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from . import gsplat_backend, native, reference
from .sh import eval_sh_colors

BACKENDS = ("native", "reference", "gsplat")
# Floor of the alpha that normalises the accumulated depth (gsplat's "ED" render mode uses the same).
DEPTH_ALPHA_EPS = 1e-10


@dataclass
class RenderResult:
    """Output of :func:`rasterize`."""

    image: Tensor  # [H, W, 3] RGB, composited over the background
    alpha: Tensor  # [H, W, 1] accumulated opacity, 1 - final transmittance
    depth: Tensor  # [H, W, 1] expected camera-frame z: sum(w_i z_i) / max(alpha, 1e-10)
    means2d: Tensor  # [N, 2] projected means (pixels); after backward, .grad is the screen-space gradient
    radii: Tensor  # [N] int32 3-sigma screen radius in pixels, 0 = culled / not visible
    backend: str = ""  # the backend that produced it ("auto" resolved)


def available_backends(device: torch.device | str = "cpu") -> list[str]:
    """Backends that can render tensors on ``device`` in this environment."""
    device = torch.device(device)
    out = []
    if device.type == "cpu" and native.is_available():
        out.append("native")
    out.append("reference")
    if device.type == "cuda" and gsplat_backend.is_available():
        out.append("gsplat")
    return out


def resolve_backend(backend: str, device: torch.device) -> str:
    """Map ``"auto"`` to a concrete backend for tensors on ``device``; validate explicit choices."""
    if backend == "auto":
        if device.type == "cuda" and gsplat_backend.is_available():
            return "gsplat"
        if device.type == "cpu" and native.is_available():
            return "native"
        return "reference"
    if backend not in BACKENDS:
        raise ValueError(f"unknown backend {backend!r}; choose from 'auto', {', '.join(map(repr, BACKENDS))}")
    if backend == "gsplat" and device.type != "cuda":
        raise ValueError("backend='gsplat' needs CUDA tensors")
    if backend == "native":
        if device.type != "cpu":
            raise ValueError("backend='native' needs CPU tensors")
        if not native.is_available():
            raise RuntimeError("backend='native' requested but the C++ extension could not be built")
    return backend


def rasterize(
    means: Tensor,  # [N, 3] world positions
    quats: Tensor,  # [N, 4] wxyz rotations, normalised inside
    scales: Tensor,  # [N, 3] positive scales (already exp'd)
    opacities: Tensor,  # [N] in [0, 1] (already sigmoid'd)
    colors: Tensor,  # [N, 3] RGB, or [N, K, 3] SH coefficients when sh_degree is given
    viewmat: Tensor,  # [4, 4] world-to-camera, OpenCV axes (x right, y down, z forward)
    K: Tensor,  # [3, 3] pinhole intrinsics; pixel (i, j) has its centre at (j + 0.5, i + 0.5)
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    background: Tensor | None = None,  # [3], None = black
    backend: str = "auto",
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> RenderResult:
    """Render 3D Gaussians from one pinhole camera, differentiably.

    Differentiable w.r.t. means, quats, scales, opacities and colors (RGB or SH coefficients);
    the image is ``sum_i w_i c_i + (1 - alpha) * background`` with gsplat's classic numerics.
    The CPU backends compute in float32 (the reference also in the input dtype).
    """
    backend = resolve_backend(backend, means.device)
    if sh_degree is None and colors.dim() != 2:
        raise ValueError(f"colors must be [N, 3] without sh_degree, got {tuple(colors.shape)}")

    if backend == "gsplat":
        image, alpha, depth, means2d, radii = gsplat_backend.rasterize_gsplat(
            means, quats, scales, opacities, colors, viewmat, K, width, height,
            sh_degree=sh_degree, background=background,
            near_plane=near_plane, far_plane=far_plane, eps2d=eps2d,
        )  # fmt: skip
        return RenderResult(image, alpha, depth, means2d, radii, backend)

    if sh_degree is None:
        rgb = colors
    elif backend == "native":
        rgb = native.sh_colors_native(means, colors, viewmat, sh_degree)  # [N, 3]
    else:
        rgb = eval_sh_colors(means, colors, viewmat, sh_degree)
    if backend == "native":
        proj = native.project_native(
            means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane, eps2d
        )
        blend = native.rasterize_native
    else:
        proj = reference.project_gaussians(
            means, quats, scales, opacities, viewmat, K, width, height, near_plane, far_plane, eps2d
        )
        blend = reference.rasterize_reference
    means2d = proj.means2d
    if means2d.requires_grad:
        means2d.retain_grad()
    color, alpha, depth_acc = blend(
        means2d, proj.conics, rgb, opacities, proj.depths, proj.extents, proj.radii, width, height
    )
    image = color
    if background is not None:
        image = color + (1.0 - alpha) * background.to(color).reshape(1, 1, 3)
    depth = depth_acc / alpha.clamp_min(DEPTH_ALPHA_EPS)
    return RenderResult(image, alpha, depth, means2d, proj.radii, backend)
