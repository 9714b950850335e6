"""Quaternion (w, x, y, z) and rotation-matrix helpers (conversions by kornia).

``normalize_quat`` stays hand-written: kornia's ``normalize_quaternion`` maps the zero quaternion
to zero (not the identity) and squares the components, so norms of 1e300 overflow.
"""

from __future__ import annotations

import torch
from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion


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
    return quaternion_to_rotation_matrix(normalize_quat(q))


def rotmat_to_quat(R: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotation matrices -> (..., 4) unit quaternions w-x-y-z with w >= 0.

    kornia's conversion takes the trace branch when the trace is positive, else the branch of
    the largest diagonal entry, stable for every rotation; the sign is made w >= 0 here.
    """
    q = rotation_matrix_to_quaternion(R)
    return normalize_quat(torch.where(q[..., :1] < 0, -q, q))


def covariance_3d(quats: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
    """(N, 3, 3) covariances R diag(s^2) R^T from (N, 4) quaternions and (N, 3) scales."""
    R = quat_to_rotmat(quats)
    M = R * scales[:, None, :]
    return M @ M.transpose(-1, -2)
