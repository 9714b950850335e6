"""Quaternion (w, x, y, z) and rotation-matrix helpers."""

from __future__ import annotations

import torch


def normalize_quat(q: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """(..., 4) -> unit quaternions; one of norm <= eps (e.g. all zero) maps to the identity
    (1, 0, 0, 0). Any finite magnitude works (1e300 in float64, 3e38 in float32): the norm is
    taken after dividing by the largest |component|, so it cannot overflow."""
    m = q.detach().abs().amax(-1, keepdim=True).clamp_min(eps)  # the result does not depend on m
    s = q / m
    n = s.norm(dim=-1, keepdim=True)  # >= 1 wherever the true norm m * n exceeds eps
    ident = torch.zeros_like(q)
    ident[..., 0] = 1.0
    return torch.where(m * n > eps, s / n.clamp_min(1.0), ident)


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) quaternions w-x-y-z (normalised here) -> (..., 3, 3) rotation matrices."""
    w, x, y, z = normalize_quat(q).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        -1,
    ).reshape(*q.shape[:-1], 3, 3)  # fmt: skip


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions w-x-y-z with w >= 0.

    Uses the largest-diagonal branch (Shepperd's method), stable for every rotation.
    """
    m = R.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = torch.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], -1)
    case = diag.argmax(-1)
    q = torch.empty(m.shape[0], 4, dtype=R.dtype, device=R.device)
    # Each branch computes the largest component first, then the others from it.
    s0 = (1 + tr).clamp_min(1e-12).sqrt() * 2
    s1 = (1 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2]).clamp_min(1e-12).sqrt() * 2
    s2 = (1 - m[:, 0, 0] + m[:, 1, 1] - m[:, 2, 2]).clamp_min(1e-12).sqrt() * 2
    s3 = (1 - m[:, 0, 0] - m[:, 1, 1] + m[:, 2, 2]).clamp_min(1e-12).sqrt() * 2
    branches = [
        torch.stack([s0 / 4, (m[:, 2, 1] - m[:, 1, 2]) / s0, (m[:, 0, 2] - m[:, 2, 0]) / s0, (m[:, 1, 0] - m[:, 0, 1]) / s0], -1),
        torch.stack([(m[:, 2, 1] - m[:, 1, 2]) / s1, s1 / 4, (m[:, 0, 1] + m[:, 1, 0]) / s1, (m[:, 0, 2] + m[:, 2, 0]) / s1], -1),
        torch.stack([(m[:, 0, 2] - m[:, 2, 0]) / s2, (m[:, 0, 1] + m[:, 1, 0]) / s2, s2 / 4, (m[:, 1, 2] + m[:, 2, 1]) / s2], -1),
        torch.stack([(m[:, 1, 0] - m[:, 0, 1]) / s3, (m[:, 0, 2] + m[:, 2, 0]) / s3, (m[:, 1, 2] + m[:, 2, 1]) / s3, s3 / 4], -1),
    ]  # fmt: skip
    for i, b in enumerate(branches):
        sel = case == i
        q[sel] = b[sel]
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    return normalize_quat(q).reshape(*R.shape[:-2], 4)


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) covariances R diag(s^2) R^T from (N, 4) quaternions and (N, 3) scales."""
    R = quat_to_rotmat(quats)
    M = R * scales[:, None, :]
    return M @ M.transpose(-1, -2)
