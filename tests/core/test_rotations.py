"""Tests for gensplat_transforms.core.rotations (w-x-y-z quaternions <-> rotation matrices)."""

from __future__ import annotations

import math

import pytest
import torch

from gensplat_transforms.core.rotations import covariance_3d, normalize_quat, quat_to_rotmat, rotmat_to_quat

DTYPE = torch.float64
S = math.sqrt(0.5)


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)  # the few tests that draw from the global generator stay reproducible


def axis_angle_quat(axis, angle_deg: float) -> torch.Tensor:
    a = torch.as_tensor(axis, dtype=DTYPE)
    a = a / a.norm()
    h = math.radians(angle_deg) / 2
    return torch.cat([torch.tensor([math.cos(h)], dtype=DTYPE), math.sin(h) * a])


def rodrigues(axis, angle_deg: float) -> torch.Tensor:
    """Independent rotation matrix: R = I + sin(t) [k]x + (1 - cos(t)) [k]x^2."""
    k = torch.as_tensor(axis, dtype=DTYPE)
    k = k / k.norm()
    Kx = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=DTYPE)
    t = math.radians(angle_deg)
    return torch.eye(3, dtype=DTYPE) + math.sin(t) * Kx + (1 - math.cos(t)) * Kx @ Kx


EDGE_CASES = [
    ((1, 0, 0), 0.0),  # identity
    ((1, 0, 0), 180.0),
    ((0, 1, 0), 180.0),
    ((0, 0, 1), 180.0),
    ((1, 1, 0), 180.0),
    ((1, -1, 1), 180.0),
    ((0, 1, 1), 179.9999),
    ((1, 0, 0), 90.0),
    ((0, 0, 1), -90.0),
    ((0.2, 0.3, -0.9), 1e-7),
    ((3, -1, 2), 120.0),
]


def same_rotation(q1: torch.Tensor, q2: torch.Tensor, atol: float) -> None:
    """Unit quaternions equal up to the q ~ -q ambiguity."""
    q1, q2 = normalize_quat(q1), normalize_quat(q2)
    dots = (q1 * q2).sum(-1).abs()
    torch.testing.assert_close(dots, torch.ones_like(dots), rtol=0, atol=atol)


@pytest.mark.parametrize(("axis", "angle"), EDGE_CASES)
def test_edge_case_rotations_round_trip(axis, angle):
    q = axis_angle_quat(axis, angle)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(R, rodrigues(axis, angle), rtol=0, atol=1e-12)
    q2 = rotmat_to_quat(R)
    assert q2[0] >= 0
    same_rotation(q2, q, atol=1e-12)
    torch.testing.assert_close(quat_to_rotmat(q2), R, rtol=0, atol=1e-12)


def test_identity_is_exact():
    q = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=DTYPE)
    assert torch.equal(quat_to_rotmat(q), torch.eye(3, dtype=DTYPE))
    assert torch.equal(rotmat_to_quat(torch.eye(3, dtype=DTYPE)), q)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_random_quaternions_round_trip(dtype):
    q = torch.randn(2000, 4, generator=torch.Generator().manual_seed(0), dtype=dtype)
    R = quat_to_rotmat(q)
    q2 = rotmat_to_quat(R)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    assert q2.dtype == dtype and (q2[:, 0] >= 0).all()
    same_rotation(q2, q, atol=tol)
    torch.testing.assert_close(q2.norm(dim=-1), torch.ones(2000, dtype=dtype), rtol=0, atol=tol)
    torch.testing.assert_close(quat_to_rotmat(q2), R, rtol=0, atol=10 * tol)


def test_random_rotation_matrices_round_trip():
    g = torch.Generator().manual_seed(1)
    Q, Rr = torch.linalg.qr(torch.randn(500, 3, 3, generator=g, dtype=DTYPE))
    Q = Q * torch.sign(torch.diagonal(Rr, dim1=-2, dim2=-1))[:, None, :]
    Q[torch.linalg.det(Q) < 0, :, 0] *= -1  # proper rotations only
    torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(Q)), Q, rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_rotmats_are_orthonormal_with_det_one(dtype):
    q = torch.randn(1000, 4, generator=torch.Generator().manual_seed(2), dtype=dtype) * 5  # unnormalised
    R = quat_to_rotmat(q)
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    eye = torch.eye(3, dtype=dtype).expand(1000, 3, 3)
    torch.testing.assert_close(R @ R.transpose(-1, -2), eye, rtol=0, atol=tol)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(1000, dtype=dtype), rtol=0, atol=tol)
    torch.testing.assert_close(
        R, quat_to_rotmat(q / q.norm(dim=-1, keepdim=True)), rtol=0, atol=tol
    )  # scale-free


def test_zero_quaternion_is_identity():
    z = torch.zeros(3, 4, dtype=DTYPE)
    torch.testing.assert_close(normalize_quat(z), torch.tensor([[1.0, 0, 0, 0]] * 3, dtype=DTYPE))
    torch.testing.assert_close(quat_to_rotmat(z), torch.eye(3, dtype=DTYPE).expand(3, 3, 3))


@pytest.mark.parametrize(("dtype", "factor"), [(torch.float64, 1e300), (torch.float64, 1e-7),
                                              (torch.float32, 1e38), (torch.float32, 1e-7)])  # fmt: skip
def test_any_finite_magnitude_normalises_with_finite_gradients(dtype, factor):
    """Squaring 1e300 (or 1e38 in float32) would overflow the norm; a norm of 1e-7 is above
    the identity threshold 1e-8, so the direction is kept."""
    q = torch.tensor([[0.9, 0.1, -0.3, 0.2], [0.0, 0.0, 3.0, 0.0]], dtype=torch.float64)
    unit = q / q.norm(dim=-1, keepdim=True)
    big = (q * factor).to(dtype).requires_grad_(True)
    out = normalize_quat(big)
    torch.testing.assert_close(out, unit.to(dtype))
    out[:, 1].sum().backward()
    assert torch.isfinite(big.grad).all()
    torch.testing.assert_close(normalize_quat(torch.tensor([[5e-9, 0, 0, 0]], dtype=dtype)),
                               torch.tensor([[1.0, 0, 0, 0]], dtype=dtype))  # fmt: skip


def test_convention_is_w_first_and_right_handed():
    q = axis_angle_quat((1, 0, 0), 90.0)  # (cos 45, sin 45, 0, 0)
    torch.testing.assert_close(q, torch.tensor([S, S, 0, 0], dtype=DTYPE))
    R = quat_to_rotmat(q)
    torch.testing.assert_close(
        R @ torch.tensor([0.0, 1.0, 0.0], dtype=DTYPE), torch.tensor([0.0, 0.0, 1.0], dtype=DTYPE)
    )


def test_batch_shapes_are_preserved():
    q = torch.randn(2, 5, 4, dtype=DTYPE)
    R = quat_to_rotmat(q)
    assert R.shape == (2, 5, 3, 3) and rotmat_to_quat(R).shape == (2, 5, 4)
    assert rotmat_to_quat(torch.zeros(0, 3, 3, dtype=DTYPE)).shape == (0, 4)


def test_covariance_3d():
    q = torch.randn(20, 4, generator=torch.Generator().manual_seed(3), dtype=DTYPE)
    s = torch.rand(20, 3, dtype=DTYPE) + 0.01
    cov = covariance_3d(q, s)
    R = quat_to_rotmat(q)
    torch.testing.assert_close(cov, R @ torch.diag_embed(s**2) @ R.transpose(-1, -2))
    torch.testing.assert_close(cov, cov.transpose(-1, -2))
    eig = torch.linalg.eigvalsh(cov)
    torch.testing.assert_close(eig, (s**2).sort(-1).values)  # principal variances are the squared scales
