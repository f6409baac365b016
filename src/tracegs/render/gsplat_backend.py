"""CUDA backend: a thin adapter from :func:`tracegs.render.rasterize` to ``gsplat.rasterization``.

gsplat is imported lazily, so CPU-only installs never need it. The CPU backends reproduce gsplat's
classic (non-antialiased) numerics; see docs/RASTERIZER.md for where the two can still differ.
"""

from __future__ import annotations

from torch import Tensor


def is_available() -> bool:
    """Whether ``gsplat`` can be imported (its CUDA kernels build on first use)."""
    try:
        import gsplat  # noqa: F401
    except Exception:  # noqa: BLE001 - a broken install is as good as none
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
