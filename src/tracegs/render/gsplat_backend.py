"""CUDA backend: a thin adapter from :func:`tracegs.render.rasterize` to ``gsplat.rasterization``.

gsplat is imported lazily, so CPU-only installs never need it. The CPU backends reproduce gsplat's
classic (non-antialiased) numerics; see docs/RASTERIZER.md for where the two can still differ.
"""

from __future__ import annotations

import functools
import warnings

from torch import Tensor


@functools.cache
def is_available() -> bool:
    """Whether gsplat's CUDA kernels load. The first call on a machine builds them (a few minutes,
    cached by PyTorch in ``~/.cache/torch_extensions``); only CUDA runs ask, so CPU runs never do.

    ``import gsplat`` alone is not enough: a wheel without prebuilt kernels imports fine and fails
    at the first render when the CUDA toolkit is missing or the build breaks. Then this warns once,
    and ``rasterize(backend="auto")`` renders CUDA tensors with the pure-PyTorch reference backend.
    """
    try:
        import gsplat  # noqa: F401
    except Exception:  # noqa: BLE001 - a broken install is as good as none
        return False
    try:
        from gsplat.cuda._backend import _C
    except Exception as err:  # noqa: BLE001 - any build or import failure means no kernels
        _C, reason = None, f"{type(err).__name__}: {err}"
    else:
        reason = "no CUDA toolkit (nvcc) to build them"
    if _C is None:
        warnings.warn(
            f"gsplat is installed but its CUDA kernels could not be loaded ({reason}); CUDA tensors "
            "are rendered with the slower pure-PyTorch 'reference' backend",
            RuntimeWarning,
            stacklevel=2,
        )
        return False
    return True


def rasterize_gsplat(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4]
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    colors: Tensor,  # [N, 3] or [N, K, 3]
    viewmat: Tensor,  # [4, 4]
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    *,
    sh_degree: int | None,
    background: Tensor | None,  # [3]
    near_plane: float,
    far_plane: float,
    eps2d: float,
):
    """Render with gsplat. Returns (image [H, W, 3], alpha [H, W, 1], depth [H, W, 1], means2d [N, 2], radii [N])."""
    from gsplat import rasterization

    renders, alphas, meta = rasterization(
        means=means,
        quats=quats,
        scales=scales,
        opacities=opacities,
        colors=colors,
        viewmats=viewmat[None],
        Ks=K[None],
        width=width,
        height=height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        sh_degree=sh_degree,
        backgrounds=None if background is None else background.reshape(1, 3).to(means),
        render_mode="RGB+ED",
        rasterize_mode="classic",
        packed=False,
    )
    image, depth = renders[0, ..., :3], renders[0, ..., 3:4]
    alpha = alphas[0]
    radii = meta["radii"][0]
    if radii.dim() == 2:  # gsplat >= 1.5 returns per-axis radii [N, 2]
        radii = radii.max(dim=-1).values
    means2d_all = meta["means2d"]  # [1, N, 2]
    means2d = means2d_all[0]
    if means2d_all.requires_grad:
        # The renderer consumed means2d_all, not this view, so no gradient reaches the view on its
        # own: copy the one that reaches means2d_all. retain_grad() lets callers read .grad without
        # the non-leaf warning (and accumulates if they also use means2d in their loss).
        means2d.retain_grad()

        def _copy_grad(grad: Tensor, _view: Tensor = means2d) -> None:
            _view.grad = grad[0] if _view.grad is None else _view.grad + grad[0]

        means2d_all.register_hook(_copy_grad)
    return image, alpha, depth, means2d, radii
