"""The RGB-D discs on a real stereo pair with ground-truth depth (scikit-image's Middlebury
"motorcycle", a quarter of its size): the left view rendered at the right camera is closer
to the real right image than a forward warp of the same depth, on the pixels the warp fills."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.rendering import render
from gensplat_transforms.rendering.holes import fill_holes
from gensplat_transforms.rendering.warp import forward_warp

pytest.importorskip("skimage", reason="the Middlebury pair needs scikit-image (the bench extra)")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from real_geometry import middlebury


@pytest.fixture(scope="module")
def pair():
    p = middlebury(0.25)
    images = torch.from_numpy(p["images"]).permute(0, 3, 1, 2).float() / 255
    depths = torch.from_numpy(p["depths"])[:, None]
    return images, depths, Cameras(p["K"], p["c2w"], depths.shape[-1], depths.shape[-2])


def test_the_default_discs_beat_the_forward_warp_by_half_a_decibel(pair):
    images, depths, cameras = pair
    warp, mask = forward_warp(images[:1], depths[:1], cameras[:1], cameras[1:])
    rec = RGBDReconstructor()(Views(images[:1], cameras[:1], depths[:1]))
    out = render(rec.gaussians, cameras[1:], backend="fast", **rec.render_options)
    truth, baseline = images[1], psnr(warp[0], images[1], mask[0])
    for view in (fill_holes(out.rgb, out.alpha)[0], out.rgb[0]):  # holes filled (the transform's default), or not
        assert psnr(view, truth, mask[0]) > baseline + 0.5
    former = RGBDReconstructor(sigma_px=0.4, edge_scale=0.25)(Views(images[:1], cameras[:1], depths[:1]))
    wide = render(former.gaussians, cameras[1:], backend="fast", **former.render_options)
    assert psnr(fill_holes(wide.rgb, wide.alpha)[0], truth, mask[0]) < baseline  # wider discs blur the texture
