"""Real spherical harmonics for view-dependent colour, in the 3D Gaussian splatting convention.

Shared by every backend (gsplat evaluates the same basis on the GPU): the colour of a Gaussian
seen from a camera is ``max(SH(d) . coeffs + 0.5, 0)`` with ``d`` the unit direction from the
camera centre to the Gaussian's mean, coefficients ordered as in 3DGS / gsplat (degree 0, then
the three degree-1 terms as -y, z, -x, ...). Only elementwise torch ops, so autograd reaches the
coefficients and, through the direction, the means.

N: Gaussians, K: SH coefficients per channel, (degree + 1)^2 <= K.
"""

from __future__ import annotations

import torch
from torch import Tensor

# Normalisation constants of the real SH basis (degree 0..3), as in 3DGS.
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (
    1.0925484305920792,
    -1.0925484305920792,
    0.31539156525252005,
    -1.0925484305920792,
    0.5462742152960396,
)
SH_C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """Number of coefficients per colour channel of an SH expansion up to ``degree``."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Evaluate the real SH basis up to ``degree`` (0..3) at unit directions.

    dirs: [N, 3] unit vectors. Returns [N, (degree + 1)^2].
    """
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        xy, yz, xz = x * y, y * z, x * z
        out += [
            SH_C2[0] * xy,
            SH_C2[1] * yz,
            SH_C2[2] * (2.0 * zz - xx - yy),
            SH_C2[3] * xz,
            SH_C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            SH_C3[0] * y * (3.0 * xx - yy),
            SH_C3[1] * xy * z,
            SH_C3[2] * y * (4.0 * zz - xx - yy),
            SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            SH_C3[4] * x * (4.0 * zz - xx - yy),
            SH_C3[5] * z * (xx - yy),
            SH_C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def check_sh_coeffs(coeffs: Tensor, degree: int) -> int:
    """The number of coefficients per channel that ``degree`` reads; ValueError where ``coeffs`` is not
    [N, K, 3] with that many or ``degree`` is not 0..3."""
    if not 0 <= degree <= 3:
        raise ValueError(f"sh_degree must be in 0..3, got {degree}")
    nb = num_sh_bases(degree)
    if coeffs.dim() != 3 or coeffs.shape[-1] != 3 or coeffs.shape[1] < nb:
        raise ValueError(
            f"SH colors must be [N, K>={nb}, 3] for sh_degree={degree}, got {tuple(coeffs.shape)}"
        )
    return nb


def camera_center(viewmat: Tensor) -> Tensor:
    """World position of the camera of a world-to-camera matrix. viewmat: [4, 4] -> [3]."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    return -(R.T @ t)


def eval_sh_colors(means: Tensor, coeffs: Tensor, viewmat: Tensor, degree: int) -> Tensor:
    """View-dependent RGB of every Gaussian (3DGS: SH + 0.5, clamped at 0).

    means: [N, 3], coeffs: [N, K, 3] with K >= (degree + 1)^2, viewmat: [4, 4]. Returns [N, 3].
    """
    nb = check_sh_coeffs(coeffs, degree)
    dirs = means - camera_center(viewmat).to(means)  # [N, 3]
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, dirs)  # [N, nb]
    rgb = (basis.unsqueeze(-1) * coeffs[:, :nb]).sum(dim=1)  # [N, 3]
    return torch.clamp_min(rgb + 0.5, 0.0)
