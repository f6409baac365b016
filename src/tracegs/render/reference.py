"""Pure-PyTorch reference rasteriser: the ground truth the fast backends are tested against.

Two stages, both plain autograd:

* :func:`project_gaussians` - EWA splatting of 3D Gaussians to 2D (means, conics, depths, radii),
  written as elementwise tensor ops. Per-Gaussian 3 x 3 products are spelled out over ``[N]`` /
  ``[N, 3]`` tensors instead of batched ``bmm``, whose CPU backward is an order of magnitude slower
  at 1e5 Gaussians.
* :func:`rasterize_reference` - 16 x 16 tiles, each blending its depth-sorted Gaussians into its
  pixels with a dense ``[pixels, Gaussians]`` alpha matrix and a cumulative product for the
  transmittance. With autograd enabled every tile is checkpointed, so memory stays at one tile's
  worth instead of ``pixels x intersections``.

Numerics are gsplat's "classic" 3DGS kernels (see docs/RASTERIZER.md): 2D covariance blurred by
``eps2d`` without opacity compensation, 3-sigma radius for culling, alpha = min(0.99, o exp(-s)),
Gaussians with alpha < 1/255 skipped, and a pixel stops before the Gaussian that would take its
transmittance to <= 1e-4.

N: Gaussians, M: Gaussians of one tile, P: pixels of one tile, H x W: image.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

TILE_SIZE = 16
MAX_ALPHA = 0.99
ALPHA_THRESHOLD = 1.0 / 255.0
TRANSMITTANCE_THRESHOLD = 1e-4
# Slack (pixels) around the alpha >= 1/255 box used for tile binning; same value as the C++ backend.
BOX_SLACK = 1e-2


@dataclass
class Projection:
    """Screen-space Gaussians. Culled Gaussians (radius 0) have zero means2d / conics / depths."""

    means2d: Tensor  # [N, 2] pixel coordinates of the projected means
    conics: Tensor  # [N, 3] inverse 2D covariance (a, b, c): sigma = a dx^2 / 2 + b dx dy + c dy^2 / 2
    depths: Tensor  # [N] camera-frame z
    radii: Tensor  # [N] int32, 3-sigma radius in pixels, 0 = culled
    extents: Tensor  # [N, 2] half-widths of the alpha >= 1/255 box (no grad), -1 = never visible


def quat_to_rotmat_rows(quats: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Rows of the rotation matrices of (not necessarily unit) wxyz quaternions.

    quats: [N, 4]. Returns three [N, 3] tensors, row i of every R.
    """
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    r0 = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], dim=-1)
    r1 = torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], dim=-1)
    r2 = torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], dim=-1)
    return r0, r1, r2


def project_gaussians(
    means: Tensor,  # [N, 3]
    quats: Tensor,  # [N, 4] wxyz
    scales: Tensor,  # [N, 3]
    opacities: Tensor,  # [N]
    viewmat: Tensor,  # [4, 4] world-to-camera
    K: Tensor,  # [3, 3]
    width: int,
    height: int,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
) -> Projection:
    """EWA projection of 3D Gaussians (gsplat's ``fully_fused_projection``, pinhole, no compensation)."""
    Rc = viewmat[:3, :3].to(means)
    tc = viewmat[:3, 3].to(means)
    fx, fy, cx, cy = (float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))

    pc = means @ Rc.T + tc  # [N, 3] camera-frame means
    x, y, z = pc.unbind(-1)
    in_range = (z >= near_plane) & (z <= far_plane)
    # Culled Gaussians still flow through the maths (masked at the end); give them a harmless depth
    # so that no inf / nan reaches the backward pass through torch.where.
    z = torch.where(in_range, z, torch.ones_like(z))

    # M = R diag(s), rotated into the camera frame: V = Rc M, kept as rows V_i [N, 3].
    r0, r1, r2 = quat_to_rotmat_rows(quats)
    m_rows = (r0 * scales, r1 * scales, r2 * scales)
    v_rows = [Rc[i, 0] * m_rows[0] + Rc[i, 1] * m_rows[1] + Rc[i, 2] * m_rows[2] for i in range(3)]

    # Jacobian of the pinhole projection, x/z and y/z clamped to 1.3x the field of view (gsplat).
    tan_fovx, tan_fovy = 0.5 * width / fx, 0.5 * height / fy
    lim_x_pos, lim_x_neg = (width - cx) / fx + 0.3 * tan_fovx, cx / fx + 0.3 * tan_fovx
    lim_y_pos, lim_y_neg = (height - cy) / fy + 0.3 * tan_fovy, cy / fy + 0.3 * tan_fovy
    rz = 1.0 / z
    tx = z * (x * rz).clamp(-lim_x_neg, lim_x_pos)
    ty = z * (y * rz).clamp(-lim_y_neg, lim_y_pos)
    j00, j02 = fx * rz, -fx * tx * rz * rz
    j11, j12 = fy * rz, -fy * ty * rz * rz

    # 2D covariance = P P^T with P = J V (2 x 3), blurred by eps2d.
    p0 = j00[:, None] * v_rows[0] + j02[:, None] * v_rows[2]  # [N, 3]
    p1 = j11[:, None] * v_rows[1] + j12[:, None] * v_rows[2]  # [N, 3]
    a = (p0 * p0).sum(-1) + eps2d
    b = (p0 * p1).sum(-1)
    c = (p1 * p1).sum(-1) + eps2d
    det = a * c - b * b
    det_ok = det > 0
    det = torch.where(det_ok, det, torch.ones_like(det))
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    means2d = torch.stack([fx * x * rz + cx, fy * y * rz + cy], dim=-1)

    with torch.no_grad():
        half = 0.5 * (a + c)
        v1 = half + torch.sqrt(torch.clamp_min(half * half - det, 0.01))
        radius = torch.ceil(3.0 * torch.sqrt(v1))
        mx, my = means2d[:, 0], means2d[:, 1]
        on_screen = (mx + radius > 0) & (mx - radius < width) & (my + radius > 0) & (my - radius < height)
        visible = in_range & det_ok & (radius > 0) & on_screen
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
        # alpha >= 1/255  <=>  d^T conic d <= 2 log(255 o): the ellipse's half-widths are
        # sqrt(2 log(255 o) cov_xx) and sqrt(2 log(255 o) cov_yy).
        o = opacities.detach().to(a)
        m = 2.0 * torch.log(torch.clamp_min(255.0 * o, 1.0))
        extents = torch.stack([torch.sqrt(m * a), torch.sqrt(m * c)], dim=-1)
        extents = torch.where(
            (visible & (o >= ALPHA_THRESHOLD))[:, None], extents, torch.full_like(extents, -1.0)
        )

    vis = visible[:, None]
    return Projection(
        means2d=torch.where(vis, means2d, torch.zeros_like(means2d)),
        conics=torch.where(vis, conics, torch.zeros_like(conics)),
        depths=torch.where(visible, z, torch.zeros_like(z)),
        radii=radii,
        extents=extents,
    )


def pixel_ranges(centers: Tensor, extents: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Inclusive index range of the pixels whose centres (j + 0.5) lie within ``extents`` of ``centers``."""
    e = extents + BOX_SLACK
    lo = torch.ceil(centers - e - 0.5).clamp_min(0).long()
    hi = torch.floor(centers + e - 0.5).clamp_max(size - 1).long()
    return lo, hi


def _blend_tile(
    px: Tensor,  # [P] pixel centre x
    py: Tensor,  # [P] pixel centre y
    means2d: Tensor,  # [M, 2] front to back
    conics: Tensor,  # [M, 3]
    colors: Tensor,  # [M, 3]
    opacities: Tensor,  # [M]
    depths: Tensor,  # [M]
) -> tuple[Tensor, Tensor, Tensor]:
    """Front-to-back alpha blending of one tile. Returns color [P, 3], alpha [P], depth_acc [P]."""
    dx = means2d[None, :, 0] - px[:, None]  # [P, M]
    dy = means2d[None, :, 1] - py[:, None]
    sigma = 0.5 * (conics[:, 0] * dx * dx + conics[:, 2] * dy * dy) + conics[:, 1] * dx * dy
    alpha = torch.clamp(opacities * torch.exp(-sigma), max=MAX_ALPHA)
    with torch.no_grad():
        hit = (sigma >= 0) & (alpha >= ALPHA_THRESHOLD)
        # A pixel stops before the Gaussian that would take T to <= 1e-4; T only decreases, so the
        # blended set is the prefix where the running product stays above the threshold.
        t_after = torch.cumprod(torch.where(hit, 1.0 - alpha, torch.ones_like(alpha)), dim=1)
        blend = hit & (t_after > TRANSMITTANCE_THRESHOLD)
    alpha = torch.where(blend, alpha, torch.zeros_like(alpha))
    t_incl = torch.cumprod(1.0 - alpha, dim=1)  # [P, M] transmittance after each Gaussian
    t_excl = torch.cat([torch.ones_like(t_incl[:, :1]), t_incl[:, :-1]], dim=1)
    w = alpha * t_excl  # [P, M] blending weights
    return w @ colors, 1.0 - t_incl[:, -1], w @ depths


def rasterize_reference(
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
    """Tile-based blending. Returns color [H, W, 3] (no background), alpha [H, W, 1], depth_acc [H, W, 1]."""
    device, dtype = means2d.device, means2d.dtype
    ids = torch.nonzero((radii > 0) & (extents[:, 0] >= 0)).squeeze(1)
    ids = ids[torch.sort(depths.detach()[ids], stable=True).indices]  # front to back, ties by index
    with torch.no_grad():
        j0, j1 = pixel_ranges(means2d[ids, 0].detach(), extents[ids, 0], width)
        i0, i1 = pixel_ranges(means2d[ids, 1].detach(), extents[ids, 1], height)
        nonempty = (j0 <= j1) & (i0 <= i1)
        tx0, tx1, ty0, ty1 = j0 // TILE_SIZE, j1 // TILE_SIZE, i0 // TILE_SIZE, i1 // TILE_SIZE
    use_checkpoint = torch.is_grad_enabled() and any(
        t.requires_grad for t in (means2d, conics, colors, opacities, depths)
    )

    rows = []
    for ty in range(math.ceil(height / TILE_SIZE)):
        y_lo, y_hi = ty * TILE_SIZE, min((ty + 1) * TILE_SIZE, height)
        row_tiles = []
        for tx in range(math.ceil(width / TILE_SIZE)):
            x_lo, x_hi = tx * TILE_SIZE, min((tx + 1) * TILE_SIZE, width)
            th, tw = y_hi - y_lo, x_hi - x_lo
            sel = ids[nonempty & (tx0 <= tx) & (tx <= tx1) & (ty0 <= ty) & (ty <= ty1)]
            if sel.numel() == 0:
                zeros = torch.zeros(th, tw, 5, device=device, dtype=dtype)
                row_tiles.append(zeros)
                continue
            yy, xx = torch.meshgrid(
                torch.arange(y_lo, y_hi, device=device, dtype=dtype) + 0.5,
                torch.arange(x_lo, x_hi, device=device, dtype=dtype) + 0.5,
                indexing="ij",
            )
            args = (
                xx.reshape(-1),
                yy.reshape(-1),
                means2d[sel],
                conics[sel],
                colors[sel],
                opacities[sel],
                depths[sel],
            )
            if use_checkpoint:
                col, alp, dep = checkpoint(_blend_tile, *args, use_reentrant=False)
            else:
                col, alp, dep = _blend_tile(*args)
            row_tiles.append(torch.cat([col, alp[:, None], dep[:, None]], dim=-1).reshape(th, tw, 5))
        rows.append(torch.cat(row_tiles, dim=1))
    out = torch.cat(rows, dim=0)  # [H, W, 5]
    return out[..., :3], out[..., 3:4], out[..., 4:5]
