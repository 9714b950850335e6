"""Real spherical harmonics up to degree 4, in the layout 3DGS and gsplat use.

Colour of a Gaussian seen along unit direction d (from the camera centre to the Gaussian):
``rgb = max(0, sum_k sh[k] * Y_k(d) + 0.5)`` with ``sh`` of shape (N, (degree+1)^2, 3).
"""

from __future__ import annotations

import torch

C0 = 0.28209479177387814  # 1 / (2 sqrt(pi))
MAX_DEGREE = 4


def num_sh_bases(degree: int) -> int:
    return (degree + 1) ** 2


def sh_degree_from_bases(k: int) -> int:
    d = round(k**0.5) - 1
    if (d + 1) ** 2 != k or not 0 <= d <= MAX_DEGREE:
        raise ValueError(f"{k} SH coefficients is not (degree+1)^2 for a degree in 0..{MAX_DEGREE}")
    return d


def rgb_to_sh_dc(rgb: torch.Tensor) -> torch.Tensor:
    """DC coefficient that reproduces ``rgb`` (any view direction)."""
    return (rgb - 0.5) / C0


def sh_dc_to_rgb(dc: torch.Tensor) -> torch.Tensor:
    return dc * C0 + 0.5


def sh_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate the (degree+1)^2 real SH basis functions.

    Args:
        degree: 0..4.
        dirs: (..., 3) unit vectors.
    Returns:
        (..., (degree+1)^2) basis values, orthonormal on the sphere.
    """
    if not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"SH degree must be in 0..{MAX_DEGREE}, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        c1 = 0.4886025119029199
        out += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.31539156525252005 * (2 * zz - xx - yy),
            -1.0925484305920792 * xz,
            0.5462742152960396 * (xx - yy),
        ]
    if degree >= 3:
        out += [
            -0.5900435899266435 * y * (3 * xx - yy),
            2.890611442640554 * xy * z,
            -0.4570457994644658 * y * (4 * zz - xx - yy),
            0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
            -0.4570457994644658 * x * (4 * zz - xx - yy),
            1.445305721320277 * z * (xx - yy),
            -0.5900435899266435 * x * (xx - 3 * yy),
        ]
    if degree >= 4:
        out += [
            2.5033429417967046 * xy * (xx - yy),
            -1.7701307697799304 * yz * (3 * xx - yy),
            0.9461746957575601 * xy * (7 * zz - 1),
            -0.6690465435572892 * yz * (7 * zz - 3),
            0.10578554691520431 * (zz * (35 * zz - 30) + 3),
            -0.6690465435572892 * xz * (7 * zz - 3),
            0.47308734787878004 * (xx - yy) * (7 * zz - 1),
            -1.7701307697799304 * xz * (xx - 3 * yy),
            0.6258357354491761 * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)),
        ]
    return torch.stack(out, -1)


def eval_sh(sh: torch.Tensor, dirs: torch.Tensor, degree: int | None = None) -> torch.Tensor:
    """RGB from SH coefficients.

    Args:
        sh: (N, K, 3) coefficients, K = (d+1)^2.
        dirs: (N, 3) view directions (need not be normalised; zero vectors are safe).
        degree: evaluate only up to this degree (default: all the coefficients carry).
    Returns:
        (N, 3) colours, clamped below at 0 (as 3DGS does).
    """
    carried = sh_degree_from_bases(sh.shape[-2])
    degree = carried if degree is None else min(degree, carried)
    if degree == 0:
        return (C0 * sh[:, 0] + 0.5).clamp_min(0.0)
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    basis = sh_basis(degree, d)  # (N, K')
    rgb = torch.einsum("nk,nkc->nc", basis, sh[:, : num_sh_bases(degree)])
    return (rgb + 0.5).clamp_min(0.0)
