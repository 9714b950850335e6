"""Frame changes for predicted Gaussians and cameras, and intrinsics from point maps."""

from __future__ import annotations

import torch
from kornia.geometry.quaternion import Quaternion

from ...core.gaussians import Gaussians
from ...core.rotations import rotmat_to_quat
from ...core.sh import sh_basis, sh_degree_from_bases


def quat_mul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product a * b of (..., 4) w-x-y-z quaternions (rotation b, then a); broadcasts."""
    return (Quaternion(a) * Quaternion(b)).data


def _fibonacci_sphere(n: int, device=None) -> torch.Tensor:
    i = torch.arange(n, dtype=torch.float64, device=device) + 0.5
    z = 1 - 2 * i / n
    phi = torch.pi * (3 - 5**0.5) * i
    r = (1 - z * z).sqrt()
    return torch.stack([r * phi.cos(), r * phi.sin(), z], dim=-1)


def sh_rotation(R: torch.Tensor, k: int) -> torch.Tensor:
    """(..., K, K) matrices A with c_new = A c for SH coefficients when the frame rotates by R.

    Colour along direction d in the new frame must equal the old colour along R^T d. The real
    SH basis transforms linearly, Y(R^T d) = M Y(d) (block-diagonal per band), so A = M^T; it
    is solved by least squares on a fixed direction set (exact up to float error).

    Args:
        R: (..., 3, 3) rotations from the old to the new frame.
        k: number of SH coefficients (degree + 1)^2.
    """
    degree = sh_degree_from_bases(k)
    dirs = _fibonacci_sphere(4 * k, device=R.device)
    Y = sh_basis(degree, dirs).to(R.dtype)  # (S, K)
    Y_rot = sh_basis(degree, dirs.to(R.dtype) @ R)  # (..., S, K); row s is Y(R^T d_s)
    return torch.linalg.pinv(Y) @ Y_rot


def transform_gaussians(
    g: Gaussians, scale: float | torch.Tensor, R: torch.Tensor, t: torch.Tensor
) -> Gaussians:
    """Gaussians under x -> scale * R x + t (means, orientations, sizes and view-dependent colour)."""
    R, t = R.to(g.dtype), t.to(g.dtype)
    sh = g.sh if g.sh.shape[1] == 1 else sh_rotation(R, g.sh.shape[1]) @ g.sh
    return Gaussians(
        means=scale * g.means @ R.T + t,
        quats=quat_mul(rotmat_to_quat(R).expand_as(g.quats), g.quats),
        scales=scale * g.scales,
        opacities=g.opacities,
        sh=sh,
    )


def estimate_focal(local_points: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
    """Least-squares focal length (pixels, fx = fy) of each view from its camera-frame point map,
    principal point at the image centre: minimises sum w |(u - cx, v - cy) - f (x, y) / z|^2.

    Args:
        local_points: (V, H, W, 3) with z > 0.
        weights: (V, H, W) non-negative, e.g. sigmoid(conf); None weighs pixels equally.
    Returns:
        (V,) focal lengths.
    """
    V, H, W, _ = local_points.shape
    dtype, dev = local_points.dtype, local_points.device
    v, u = torch.meshgrid(
        torch.arange(H, dtype=dtype, device=dev) + 0.5 - H / 2,
        torch.arange(W, dtype=dtype, device=dev) + 0.5 - W / 2,
        indexing="ij",
    )
    ray = local_points[..., :2] / local_points[..., 2:].clamp_min(1e-8)
    w = torch.ones(V, H, W, dtype=dtype, device=dev) if weights is None else weights.to(dtype)
    num = (w * (u * ray[..., 0] + v * ray[..., 1])).sum((1, 2))
    den = (w * (ray**2).sum(-1)).sum((1, 2)).clamp_min(1e-12)
    return num / den


def align_similarity(
    source: torch.Tensor, target: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Similarity (scale, R, t) taking camera-to-world poses ``source`` onto ``target``.

    R is the rotation nearest to sum_i R_target_i R_source_i^T; the scale is the ratio of the
    camera centres' spreads (1 for a single camera, whose scale is unobservable); t matches the
    centroids.

    Args:
        source, target: (V, 4, 4) camera-to-world.
    Returns:
        scale (), R (3, 3), t (3,), with target_i ~ [scale R | t] source_i.
    """
    m = (target[:, :3, :3] @ source[:, :3, :3].transpose(1, 2)).sum(0)
    u, _, vh = torch.linalg.svd(m)
    d = torch.det(u @ vh)
    R = u @ torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d])) @ vh
    cs, ct = source[:, :3, 3], target[:, :3, 3]
    spread_s = (cs - cs.mean(0)).square().sum()
    spread_t = (ct - ct.mean(0)).square().sum()
    scale = (
        (spread_t / spread_s).sqrt() if len(source) > 1 and spread_s > 1e-12 else torch.ones_like(spread_s)
    )
    t = ct.mean(0) - scale * R @ cs.mean(0)
    return scale, R, t


def transform_poses(c2w: torch.Tensor, scale: torch.Tensor, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(V, 4, 4) camera-to-world poses under x -> scale * R x + t (rotations stay orthonormal)."""
    out = c2w.clone()
    out[:, :3, :3] = R @ c2w[:, :3, :3]
    out[:, :3, 3] = scale * c2w[:, :3, 3] @ R.T + t
    return out
