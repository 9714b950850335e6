"""Tests for gensplat_transforms.core.sh (real spherical harmonics, 3DGS / gsplat layout)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from gensplat_transforms.core.rotations import quat_to_rotmat
from gensplat_transforms.core.sh import (
    C0,
    MAX_DEGREE,
    eval_sh,
    num_sh_bases,
    rgb_to_sh_dc,
    sh_basis,
    sh_dc_to_rgb,
    sh_degree_from_bases,
)

DTYPE = torch.float64


@pytest.fixture(autouse=True)
def _seed():
    torch.manual_seed(0)  # the few tests that draw from the global generator stay reproducible


def sphere_quadrature(n_theta: int = 10, n_phi: int = 18) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions and weights that integrate every spherical polynomial of degree <= 2*n_theta - 1
    (and azimuthal order < n_phi) exactly: Gauss-Legendre in cos(theta) x uniform in phi."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = 2 * math.pi * np.arange(n_phi) / n_phi
    z, phi = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - z**2)
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).reshape(-1, 3)
    w = np.repeat(wz, n_phi) * (2 * math.pi / n_phi)
    return torch.from_numpy(dirs), torch.from_numpy(w)


def random_dirs(n: int, seed: int = 0) -> torch.Tensor:
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=DTYPE)
    return d / d.norm(dim=-1, keepdim=True)


def reference_basis(degree: int, dirs: torch.Tensor) -> torch.Tensor:
    """Independent textbook real SH: associated Legendre recursion with the Condon-Shortley phase;
    index ell*ell + ell + m holds sqrt(2) N P_l^|m| cos(m phi) for m > 0, sin(|m| phi) for m < 0."""
    x, y, z = dirs.unbind(-1)
    phi, s = torch.atan2(y, x), torch.sqrt((1 - z * z).clamp_min(0))
    P = {}
    for m in range(degree + 1):
        P[m, m] = (-1) ** m * math.prod(range(1, 2 * m, 2)) * s**m
        if m < degree:
            P[m + 1, m] = z * (2 * m + 1) * P[m, m]
        for ell in range(m + 2, degree + 1):
            P[ell, m] = ((2 * ell - 1) * z * P[ell - 1, m] - (ell + m - 1) * P[ell - 2, m]) / (ell - m)
    out = []
    for ell in range(degree + 1):
        for m in range(-ell, ell + 1):
            a = abs(m)
            norm = math.sqrt(
                (2 * ell + 1) / (4 * math.pi) * math.factorial(ell - a) / math.factorial(ell + a)
            )
            if m == 0:
                out.append(norm * P[ell, 0])
            else:
                trig = torch.cos(a * phi) if m > 0 else torch.sin(a * phi)
                out.append(math.sqrt(2) * norm * P[ell, a] * trig)
    return torch.stack(out, -1)


# ---------------------------------------------------------------------------- the basis
def test_basis_is_orthonormal_on_the_sphere():
    # Products of two degree <= 4 harmonics are spherical polynomials of degree <= 8 with
    # azimuthal order <= 8: 10 Gauss-Legendre nodes (exact to degree 19 in cos theta) times
    # 18 uniform azimuths (exact for orders < 18) integrate them exactly, so the only error
    # left is float64 round-off: 1e-12 is a safe bound for sums of 180 terms of size ~1.
    dirs, w = sphere_quadrature()
    assert float(w.sum()) == pytest.approx(4 * math.pi, abs=1e-12)
    Y = sh_basis(MAX_DEGREE, dirs)
    gram = Y.T @ (w[:, None] * Y)
    torch.testing.assert_close(gram, torch.eye(25, dtype=DTYPE), rtol=0, atol=1e-12)


def test_basis_matches_an_independent_textbook_formula():
    dirs = torch.cat([random_dirs(500), torch.eye(3, dtype=DTYPE), -torch.eye(3, dtype=DTYPE)])
    torch.testing.assert_close(sh_basis(4, dirs), reference_basis(4, dirs), rtol=0, atol=1e-12)


def test_basis_follows_the_3dgs_sign_convention():
    # 3DGS / gsplat degree 1: (-C1 y, C1 z, -C1 x)
    c1 = math.sqrt(3 / (4 * math.pi))
    d = torch.tensor([[0.36, 0.48, 0.8]], dtype=DTYPE)
    torch.testing.assert_close(
        sh_basis(1, d)[0, 1:], torch.tensor([-c1 * 0.48, c1 * 0.8, -c1 * 0.36], dtype=DTYPE)
    )
    # at the north pole only the zonal (m = 0) functions are non-zero: sqrt((2l + 1) / 4 pi)
    pole = sh_basis(4, torch.tensor([[0.0, 0.0, 1.0]], dtype=DTYPE))[0]
    expected = torch.zeros(25, dtype=DTYPE)
    for ell in range(5):
        expected[ell * ell + ell] = math.sqrt((2 * ell + 1) / (4 * math.pi))
    torch.testing.assert_close(pole, expected, rtol=0, atol=1e-12)


def test_addition_theorem_and_parity():
    d = random_dirs(300, seed=1)
    Y, Y_neg = sh_basis(4, d), sh_basis(4, -d)
    for ell in range(5):
        band = slice(ell * ell, (ell + 1) ** 2)
        # sum over m of Y_lm(d)^2 is the same for every direction: the bands do not mix
        torch.testing.assert_close(
            (Y[:, band] ** 2).sum(-1), torch.full((300,), (2 * ell + 1) / (4 * math.pi), dtype=DTYPE)
        )
        torch.testing.assert_close(Y_neg[:, band], (-1) ** ell * Y[:, band])


def test_each_band_is_closed_under_rotation():
    d = random_dirs(200, seed=2)
    R = quat_to_rotmat(torch.tensor([0.3, -0.5, 0.7, 0.2], dtype=DTYPE))
    Y, Y_rot = sh_basis(4, d), sh_basis(4, d @ R.T)
    for ell in range(5):
        band = slice(ell * ell, (ell + 1) ** 2)
        D = torch.linalg.lstsq(Y[:, band], Y_rot[:, band]).solution  # Y_rot = Y D within the band
        torch.testing.assert_close(Y[:, band] @ D, Y_rot[:, band], rtol=0, atol=1e-10)
        torch.testing.assert_close(
            D.T @ D, torch.eye(2 * ell + 1, dtype=DTYPE), rtol=0, atol=1e-10
        )  # orthogonal


@pytest.mark.parametrize("degree", range(5))
def test_basis_shape_and_lower_degrees_are_prefixes(degree):
    d = random_dirs(7).reshape(7, 1, 3)
    Y = sh_basis(degree, d)
    assert Y.shape == (7, 1, num_sh_bases(degree))
    torch.testing.assert_close(Y, sh_basis(4, d)[..., : num_sh_bases(degree)])


# ---------------------------------------------------------------------------- colours
def test_degree_zero_colour_is_c0_dc_plus_half():
    assert C0 == pytest.approx(1 / (2 * math.sqrt(math.pi)))
    dc = torch.tensor([[[0.2, -0.7, 1.3]], [[-1.0, 0.0, 0.4]]], dtype=DTYPE)
    rgb = eval_sh(dc, random_dirs(2))
    torch.testing.assert_close(rgb, C0 * dc[:, 0] + 0.5)
    torch.testing.assert_close(sh_dc_to_rgb(dc[:, 0]), C0 * dc[:, 0] + 0.5)
    target = torch.tensor([[0.1, 0.5, 0.9]], dtype=DTYPE)
    torch.testing.assert_close(eval_sh(rgb_to_sh_dc(target)[:, None], random_dirs(1)), target)


def test_higher_degrees_with_zero_rest_do_not_change_the_colour():
    sh = torch.zeros(50, 25, 3, dtype=DTYPE)
    sh[:, 0] = torch.randn(50, 3, dtype=DTYPE) * 0.5
    torch.testing.assert_close(eval_sh(sh, random_dirs(50)), (C0 * sh[:, 0] + 0.5).clamp_min(0))


def test_eval_sh_matches_the_basis_sum_and_ignores_direction_length():
    sh = torch.randn(40, 16, 3, dtype=DTYPE) * 0.3
    d = random_dirs(40, seed=3)
    expected = (torch.einsum("nk,nkc->nc", sh_basis(3, d), sh) + 0.5).clamp_min(0)
    torch.testing.assert_close(eval_sh(sh, d), expected)
    torch.testing.assert_close(eval_sh(sh, 7.5 * d), expected)
    assert torch.isfinite(eval_sh(sh, torch.zeros(40, 3, dtype=DTYPE))).all()  # zero directions are safe


@pytest.mark.parametrize("degree", [0, 1, 2])
def test_eval_sh_truncates_to_a_lower_degree(degree):
    sh = torch.randn(30, 16, 3, dtype=DTYPE) * 0.3
    d = random_dirs(30, seed=4)
    k = num_sh_bases(degree)
    torch.testing.assert_close(eval_sh(sh, d, degree=degree), eval_sh(sh[:, :k].clone(), d))
    assert not torch.allclose(eval_sh(sh, d, degree=degree), eval_sh(sh, d))  # truncation changed it


def test_eval_sh_degree_above_the_carried_one_uses_what_is_there():
    sh = torch.randn(10, 4, 3, dtype=DTYPE)
    d = random_dirs(10)
    torch.testing.assert_close(eval_sh(sh, d, degree=4), eval_sh(sh, d))


def test_eval_sh_clamps_at_zero():
    sh = torch.zeros(4, 4, 3, dtype=DTYPE)
    sh[:, 0] = torch.tensor([[-10.0, 0.0, 10.0]], dtype=DTYPE)  # rgb before clamping: -2.32, 0.5, 3.32
    sh[:, 2, 1] = torch.tensor([-5.0, 5.0, 0.0, 1.0], dtype=DTYPE)  # view-dependent green via the z harmonic
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=DTYPE).expand(4, 3)
    rgb = eval_sh(sh, d)
    assert (rgb[:, 0] == 0).all()  # clamped, not negative
    torch.testing.assert_close(rgb[:, 2], torch.full((4,), 10 * C0 + 0.5, dtype=DTYPE))  # no upper clamp
    c1 = math.sqrt(3 / (4 * math.pi))
    expected_g = (torch.tensor([-5.0, 5.0, 0.0, 1.0], dtype=DTYPE) * c1 + 0.5).clamp_min(0)
    torch.testing.assert_close(rgb[:, 1], expected_g)
    assert rgb[0, 1] == 0 and rgb[1, 1] > 0.5


# ---------------------------------------------------------------------------- helpers
@pytest.mark.parametrize(("k", "degree"), [(1, 0), (4, 1), (9, 2), (16, 3), (25, 4)])
def test_degree_from_bases(k, degree):
    assert sh_degree_from_bases(k) == degree and num_sh_bases(degree) == k


@pytest.mark.parametrize("k", [0, 2, 5, 15, 36])
def test_degree_from_bad_bases_raises(k):
    with pytest.raises(ValueError, match="SH coefficients"):
        sh_degree_from_bases(k)


@pytest.mark.parametrize("degree", [-1, 5])
def test_bad_degree_raises(degree):
    with pytest.raises(ValueError, match="SH degree must be in 0..4"):
        sh_basis(degree, random_dirs(3))
