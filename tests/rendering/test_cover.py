"""``render(..., cover=)``: pixels the splats cover to at least ``cover`` show the splats' own
colour (the cracks between small RGB-D discs seen from a moved camera), the rest as composited."""

from __future__ import annotations

import math

import pytest
import torch

from gensplat_transforms import Cameras, GenSplatConfig, render
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.core.scenes import Scenes
from gensplat_transforms.core.sh import rgb_to_sh_dc
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import RGBDConfig, RGBDReconstructor, Views
from gensplat_transforms.rendering import covered
from gensplat_transforms.rendering.scenes import render_scenes
from gensplat_transforms.views.perturbation import PaperSampler


def one_splat(opacity: float, dtype=torch.float32) -> tuple[Gaussians, Cameras]:
    """A red Gaussian 1 m in front of a 9x9 camera, about a pixel wide."""
    g = Gaussians(torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype), torch.tensor([[1.0, 0, 0, 0]], dtype=dtype),
                  torch.full((1, 3), 0.1, dtype=dtype), torch.tensor([opacity], dtype=dtype),
                  rgb_to_sh_dc(torch.tensor([[[1.0, 0.0, 0.0]]], dtype=dtype)))  # fmt: skip
    return g, Cameras.from_intrinsics(10.0, 10.0, 4.5, 4.5, torch.eye(4), 9, 9)


def test_covered_divides_out_the_background_where_alpha_reaches_cover():
    rgb = torch.rand(2, 3, 5, 6, generator=torch.Generator().manual_seed(0))
    alpha = torch.rand(2, 1, 5, 6, generator=torch.Generator().manual_seed(1))
    background = torch.tensor([0.2, 0.5, 0.9])
    composited = alpha * rgb + (1 - alpha) * background.reshape(3, 1, 1)  # splat colour rgb over the background
    out, a = covered(composited, alpha, background, 0.4)
    seen = (alpha >= 0.4).expand_as(rgb)
    assert 0 < seen.float().mean() < 1
    torch.testing.assert_close(out[seen], rgb[seen])
    assert torch.equal(out[~seen], composited[~seen]) and torch.equal(a, torch.where(alpha >= 0.4, 1.0, alpha))
    same, a1 = covered(composited, alpha, background, 1.0)  # only fully covered pixels: nothing to change
    assert torch.equal(same, composited) and torch.equal(a1, alpha)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float32, torch.float64])
def test_a_half_transparent_splat_shows_its_own_colour_once_covered(dtype):
    g, camera = one_splat(0.5, dtype)
    plain = render(g, camera, background=(0.0, 0.0, 1.0))
    out = render(g, camera, background=(0.0, 0.0, 1.0), cover=0.3)
    centre = plain.alpha[0, 0, 4, 4]
    assert 0.3 < centre < 0.6 and out.alpha[0, 0, 4, 4] == 1
    torch.testing.assert_close(out.rgb[0, :, 4, 4].double(), torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                               atol=4e-3 if dtype == torch.bfloat16 else 1e-5, rtol=0)  # bf16's red: 1 - 2^-12
    far = plain.alpha[0, 0] < 0.3  # beyond the splat: as composited, blue background
    assert far.any() and torch.equal(out.rgb[0][:, far], plain.rgb[0][:, far])
    assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all()
    torch.testing.assert_close(out.depth, plain.depth)  # depth was the splats' own already


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, math.nan, math.inf])
def test_a_cover_outside_zero_one_is_refused(bad):
    g, camera = one_splat(1.0)
    with pytest.raises(ValueError, match="cover"):
        render(g, camera, cover=bad)
    with pytest.raises(ValueError, match="RGBDConfig.cover"):
        RGBDConfig(cover=bad)


def moved_views(fill_holes: bool, **render_options):
    """Two 32x32 tabletop views' discs seen from the left camera moved (``large``), as the
    transform renders them."""
    cams = default_cameras(32, 32)[:2]
    images, depths = TabletopScene(seed=2).render(cams)
    rec = RGBDReconstructor()(Views(images, cams, depths))
    target = PaperSampler("large", seed=0).sample(0).move(cams, 0)[:1]
    config = GenSplatConfig(fill_holes=fill_holes, render_options=render_options)
    return render_scenes(Scenes.of([rec]), target, config)


def test_the_transform_covers_where_holes_are_not_filled_and_fills_where_they_are():
    covered_views, composited = moved_views(False), moved_views(False, cover=1.0)
    partly = (composited.alpha > RGBDConfig.cover) & (composited.alpha < 0.99)
    assert partly.any()  # the moved camera sees between the small discs
    assert (covered_views.alpha[partly] == 1).all()
    bright = covered_views.rgb.sum(2, keepdim=True)[partly] > composited.rgb.sum(2, keepdim=True)[partly]
    assert bright.float().mean() > 0.9  # over black, no longer darkened by the background
    filled, filled_composited = moved_views(True), moved_views(True, cover=1.0)
    assert torch.equal(filled.rgb, filled_composited.rgb)  # the fill blends partly covered pixels instead
    assert torch.isfinite(covered_views.rgb).all() and torch.isfinite(filled.rgb).all()
