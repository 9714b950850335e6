"""RGB-D discs on rough (noisy) depth drawn as plain Gaussians, exact depth kept sharp
(``RGBDConfig.soften_noise``), and ``render``'s per-Gaussian saturation."""

import pytest
import torch
from tiny_model import tiny_model

from gensplat_transforms import Cameras, look_at, render
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.geometry import GeometryReconstructor, RGBDReconstructor, Views, discs_fast
from gensplat_transforms.geometry.rgbd import (
    PLAIN_DILATION,
    ROUGH_EDGE,
    ROUGH_START,
    ROUGH_WINDOW,
    RGBDConfig,
    depth_roughness,
)  # fmt: skip

H, W, F = 40, 48, 50.0


def plane_depth(tilt: tuple[float, float] = (0.3, -0.2), distance: float = 1.0) -> torch.Tensor:
    """(1, H, W) camera-z depth of the plane n . X = distance (n from ``tilt``) seen by a pinhole
    camera of focal F at the image centre."""
    u = (torch.arange(W, dtype=torch.float64) + 0.5 - W / 2) / F
    v = (torch.arange(H, dtype=torch.float64)[:, None] + 0.5 - H / 2) / F
    a, b = tilt
    return (distance / (a * u + b * v + 1)).float()[None]  # z = d / (n . (u, v, 1)), n = (a, b, 1)


def intrinsics(n: int = 1) -> torch.Tensor:
    return torch.tensor([[F, 0, W / 2], [0, F, H / 2], [0, 0, 1]]).repeat(n, 1, 1)


def both_roughness(z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    K = intrinsics(len(z))
    return depth_roughness(z.double(), K.double()), discs_fast.depth_roughness(z, K, ROUGH_EDGE, ROUGH_WINDOW)


def test_planes_and_depth_edges_are_not_rough():
    """Any tilt of a plane has no second difference of inverse depth; a curved surface's keep
    their sign; a step between two planes is an edge, not noise; holes leave no trace."""
    for tilt in ((0.0, 0.0), (0.3, -0.2), (1.5, 0.8)):
        for rho in both_roughness(plane_depth(tilt)):
            assert rho.abs().max() < 1e-3, tilt
    u = (torch.arange(W) + 0.5 - W / 2) / F
    v = (torch.arange(H)[:, None] + 0.5 - H / 2) / F
    curved = (1 + 20 * u**2 + 10 * v**2).expand(1, H, W)  # |d| about 0.4 footprints, of one sign
    for rho in both_roughness(curved):
        assert rho.max() < 0.05
    step = plane_depth()
    step[:, :, W // 2 :] *= 1.2  # a 20 % depth step: 40 footprints
    step[:, 5:9, 5:9] = 0  # a hole
    for rho in both_roughness(step):
        assert rho.max() < 1e-3


def test_noise_of_a_fraction_of_a_footprint_is_rough():
    """Depth noise of one footprint (z / f) reads as rough: about 0.7 footprints (differences
    beyond ROUGH_EDGE count as edges), above ROUGH_START everywhere inside; the twins agree."""
    g = torch.Generator().manual_seed(0)
    z = plane_depth()
    noisy = z + 1.0 * (z / F) * torch.randn(z.shape, generator=g)
    ref, fast = both_roughness(noisy)
    torch.testing.assert_close(fast, ref.float(), rtol=1e-4, atol=1e-6)
    assert ref[:, 3:-3, 3:-3].min() > ROUGH_START and ref.median() > 0.6
    quiet = z + 0.02 * (z / F) * torch.randn(z.shape, generator=g)  # a fiftieth of a footprint
    assert both_roughness(quiet)[1].max() < ROUGH_START


def test_compiled_roughness_matches_the_rule_on_hard_depth_maps():
    """Holes, lines of zeros, single pixels, depths 1e4 times nearer and farther, 1e30 m and
    1e-30 m: finite, non-negative, the two twins alike."""
    g = torch.Generator().manual_seed(1)
    z = plane_depth().repeat(2, 1, 1) * (1 + 0.004 * torch.rand(2, H, W, generator=g))
    z[0, 3:7, 4:9] = 0
    z[0, 10, :] = 0
    z[1, ::3, ::2] = 0
    z[1, 5:9, 10:14] *= 1e4
    z[1, 12:, :6] *= 1e-4
    z[0, 12:15, 18:21] = 1e30
    z[0, 20:23, 30:33] = 1e-30
    ref, fast = both_roughness(z)
    assert torch.isfinite(fast).all() and fast.min() >= 0
    torch.testing.assert_close(fast, ref.float(), rtol=1e-4, atol=1e-5)
    tiny = both_roughness(torch.zeros(1, 2, 2))[1]  # no pixel with both neighbours
    assert torch.equal(tiny, torch.zeros(1, 2, 2))


def views_of(depth: torch.Tensor) -> Views:
    """One camera at the origin looking down +z, grey image, the given (1, H, W) depth."""
    cam = Cameras(intrinsics(), torch.eye(4)[None], W, H)
    return Views(torch.full((1, 3, H, W), 0.5), cam, depth[:, None])


@pytest.mark.parametrize("fast", [True, False])
def test_noisy_depth_gives_plain_discs_and_exact_depth_sharp_ones(fast):
    """A plane from exact depth: every disc at the configured saturation, shapes untouched.
    The same plane with noise of a footprint: every interior disc softened, nearly all fully
    (saturation 1, in-plane variances grown by (PLAIN_DILATION - dilation) footprints^2); off:
    the rule's discs unchanged."""
    g = torch.Generator().manual_seed(2)
    z = plane_depth()
    exact = RGBDReconstructor(fast=fast)(views_of(z))
    assert exact.render_options["saturation"] == 2.0  # one number: nothing softened
    noisy_depth = z + 1.0 * (z / F) * torch.randn(z.shape, generator=g)
    noisy = RGBDReconstructor(fast=fast)(views_of(noisy_depth))
    sharp = RGBDReconstructor(fast=fast, soften_noise=False)(views_of(noisy_depth))
    saturation = noisy.render_options["saturation"]
    assert saturation.shape == (H * W,) and saturation.min() >= 1 and saturation.max() <= 2
    interior = torch.zeros(H, W, dtype=torch.bool)
    interior[3:-3, 3:-3] = True
    interior = interior.reshape(-1)[noisy.pixel_ids]
    assert saturation[interior].max() < 2 and (saturation[interior] == 1).float().mean() > 0.9
    interior &= saturation == 1
    footprint = noisy_depth.reshape(-1)[noisy.pixel_ids] / F
    grown = sharp.gaussians.scales[:, :2].square() + (PLAIN_DILATION - RGBDConfig.dilation) * footprint[:, None] ** 2
    torch.testing.assert_close(noisy.gaussians.scales[interior, :2], grown[interior].sqrt(), rtol=1e-5, atol=0)
    torch.testing.assert_close(noisy.gaussians.scales[:, 2], sharp.gaussians.scales[:, 2])  # thickness kept
    assert torch.equal(noisy.gaussians.opacities, sharp.gaussians.opacities)
    assert sharp.render_options["saturation"] == 2.0


def test_softened_discs_render_close_to_plain_gaussians():
    """Fully rough discs drawn with their per-disc saturation (1) and the sharp dilation come
    out closer to the same discs drawn plain (saturation 1, dilation 0.3) than the sharp
    discs (the in-plane growth stands in for the dilation, up to each disc's tilt)."""
    g = torch.Generator().manual_seed(3)
    z = plane_depth()
    noisy = z + 1.0 * (z / F) * torch.randn(z.shape, generator=g)
    views = views_of(noisy)
    views = Views(torch.rand(1, 3, H, W, generator=g), views.cameras, views.depths)
    soft = RGBDReconstructor()(views)
    sharp = RGBDReconstructor(soften_noise=False)(views)
    plain = render(sharp.gaussians, views.cameras, dilation=PLAIN_DILATION, saturation=1.0).rgb
    a = render(soft.gaussians, views.cameras, **soft.render_options).rgb
    b = render(sharp.gaussians, views.cameras, **sharp.render_options).rgb
    inner = (..., slice(4, -4), slice(4, -4))
    assert (a - plain)[inner].abs().mean() < 0.6 * (b - plain)[inner].abs().mean()  # measured: 0.035, 0.080


def test_render_takes_a_saturation_per_gaussian():
    """The same number for every Gaussian renders bit for bit as that number; each
    Gaussian's own value applies to it alone; bad values raise naming the problem."""
    g = Gaussians(torch.tensor([[-0.1, 0, 0], [0.1, 0, 0]]), torch.tensor([[1.0, 0, 0, 0]] * 2),
                  torch.full((2, 3), 0.03), torch.full((2,), 0.4), torch.rand(2, 1, 3))  # fmt: skip
    cam = Cameras.from_intrinsics(40.0, 40.0, 16.0, 16.0, look_at((0, -1, 0), (0, 0, 0)), 32, 32)
    for backend in ("fast", "reference"):
        one = render(g, cam, saturation=2.0, backend=backend)
        each = render(g, cam, saturation=torch.tensor([2.0, 2.0]), backend=backend)
        assert torch.equal(one.rgb, each.rgb) and torch.equal(one.alpha, each.alpha)
        mixed = render(g, cam, saturation=torch.tensor([2.0, 1.0]), backend=backend).alpha[0, 0]
        plain = render(g, cam, backend=backend).alpha[0, 0]
        left, right = mixed[16, :16], mixed[16, 16:]  # x = -0.1 is on the image's left
        torch.testing.assert_close(left.max(), one.alpha[0, 0, 16, :16].max())
        torch.testing.assert_close(right.max(), plain[16, 16:].max())
    for bad, match in ((torch.tensor([2.0]), r"shape \(2,\)"), (torch.tensor([2.0, 0.5]), ">= 1"),
                       (torch.tensor([2.0, float("nan")]), "finite"), (0.5, ">= 1")):  # fmt: skip
        with pytest.raises(ValueError, match=match):
            render(g, cam, saturation=bad)


def test_the_geometry_path_keeps_its_discs_sharp_unless_told():
    """A model's depth errors are not a sensor's noise: the geometry path's discs stay sharp by
    default (softening them cost its hole-filled view 1.3 dB at the source pose); asked, it
    softens them like the RGB-D path."""
    assert GeometryReconstructor(tiny_model()).discs.cfg.soften_noise is False
    assert GeometryReconstructor(tiny_model(), discs=RGBDConfig()).discs.cfg.soften_noise is True
