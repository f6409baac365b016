"""Shared scenes and a render-and-backprop helper for the rasteriser tests (imported by them)."""

from __future__ import annotations

import torch

from tracegs.render import rasterize
from tracegs.render.random_scene import random_scene

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def hard_scene(n: int, width: int, height: int, *, seed: int = 0, sh_degree: int | None = None) -> dict:
    """Random scene plus the awkward cases: Gaussians behind the camera, a few covering the whole
    image, and large ones outside gsplat's 1.3x-FOV Jacobian clamp that still reach the image."""
    sc = random_scene(n, width, height, seed=seed, sh_degree=sh_degree, scale=0.06, frac_behind=0.1)
    g = torch.Generator().manual_seed(seed + 1000)
    fx = float(sc["K"][0, 0])
    half_w = width / 2 / fx
    p_cam = torch.tensor(
        [
            [0.1, 0.0, 3.0],  # covers the whole image
            [-0.2, 0.1, 5.0],  # covers the whole image
            [1.6 * half_w * 3.0, 0.0, 3.0],  # centre outside the clamp, radius reaching in
            [-1.7 * half_w * 4.0, 0.3, 4.0],
        ],
        dtype=torch.float64,
    )
    R, t = sc["viewmat"][:3, :3].double(), sc["viewmat"][:3, 3].double()
    extra = {
        "means": ((p_cam - t) @ R).float(),
        "quats": torch.randn(4, 4, generator=g),
        "scales": torch.tensor([[2.0, 1.5, 1.0], [3.0, 2.0, 2.5], [0.8, 0.6, 0.7], [1.0, 0.9, 0.8]]),
        "opacities": torch.tensor([1.0, 0.95, 0.6, 0.4]),  # the first two saturate: alpha clamp, early stop
    }
    if sh_degree is None:
        extra["colors"] = torch.rand(4, 3, generator=g)
    else:
        extra["colors"] = 0.3 * torch.randn(4, sc["colors"].shape[1], 3, generator=g)
    for k, v in extra.items():
        sc[k] = torch.cat([sc[k], v.to(sc[k].dtype)], dim=0)
    return sc


def render_with_grads(scene: dict, backend: str, *, background=None, seed: int = 7) -> dict:
    """Render, backprop a loss touching image, alpha and depth; return outputs and every gradient."""
    leaves = {k: scene[k].detach().clone().requires_grad_(True) for k in PARAMS}
    rest = {k: v for k, v in scene.items() if k not in PARAMS}
    out = rasterize(**leaves, **rest, backend=backend, background=background)
    g = torch.Generator().manual_seed(seed)
    H, W = out.image.shape[:2]
    w_img = torch.rand(H, W, 3, generator=g, dtype=out.image.dtype).to(out.image.device)
    w_alpha = torch.rand(H, W, 1, generator=g, dtype=out.image.dtype).to(out.image.device)
    loss = (out.image * w_img).sum() + 0.5 * (out.alpha * w_alpha).sum() + 0.1 * out.depth.mean()
    loss.backward()
    res = {"image": out.image.detach(), "alpha": out.alpha.detach(), "depth": out.depth.detach()}
    res["radii"] = out.radii
    res["means2d"] = out.means2d.detach()
    res["grad_means2d"] = out.means2d.grad
    for k, v in leaves.items():
        res["grad_" + k] = v.grad
    return res


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    """max |a - b| / max |b| (b the reference)."""
    return ((a.double() - b.double()).abs().max() / b.double().abs().max().clamp_min(1e-30)).item()


def native_available() -> bool:
    from tracegs.render import native

    return native.is_available()
