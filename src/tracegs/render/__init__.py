"""Differentiable Gaussian rasterisation: one entry point, CPU backends and the gsplat CUDA backend.

>>> from tracegs.render import rasterize
>>> out = rasterize(means, quats, scales, opacities, colors, viewmat, K, width, height)
>>> out.image  # [H, W, 3]

See :func:`rasterize` for the arguments and docs/RASTERIZER.md for the design.
"""

from .rendering import RenderResult, available_backends, rasterize
from .sh import eval_sh_colors, sh_basis

__all__ = ["RenderResult", "available_backends", "eval_sh_colors", "rasterize", "sh_basis"]
