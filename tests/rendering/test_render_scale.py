"""Augmented views built and rendered at a fraction of the image size (``render_scale``), in
the worker and in the batch path, for depth and Gaussian caches."""

import math
from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F
from torch.utils.data import default_collate

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.geometry import Reconstructor, RGBDReconstructor, Views
from gensplat_transforms.geometry.base import nearest_pixels
from gensplat_transforms.rendering import scenes as view_output
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform, render_size

LEFT, RIGHT = "observation.images.left", "observation.images.right"


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    source = SceneEpisodes(num_episodes=1, num_frames=3, size=48)
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, [0], progress=False)
    return cache, source


class StoredRGBD(Reconstructor):
    """RGB-D discs stored as Gaussians (a cache of kind "gaussians", as the model's)."""

    name = "stored-rgbd"

    def config(self) -> dict:
        return {}

    def reconstruct(self, views):
        return RGBDReconstructor()(views)


def sizes_rendered(monkeypatch) -> list[tuple[int, int]]:
    """Records the (width, height) of every camera the transform renders."""
    seen, render = [], view_output.render

    def spy(gaussians, camera, **kwargs):
        seen.append((camera.width, camera.height))
        return render(gaussians, camera, **kwargs)

    monkeypatch.setattr(view_output, "render", spy)
    return seen


def test_nearest_pixels_is_pytorchs_nearest_exact_for_any_dtype():
    x = torch.randn(2, 3, 37, 53)
    for width, height in ((17, 11), (53, 37), (20, 30), (1, 1), (106, 74)):
        expected = F.interpolate(x, size=(height, width), mode="nearest-exact")
        assert torch.equal(nearest_pixels(x, width, height), expected)
    words = torch.randint(-32768, 32767, (2, 37, 53), dtype=torch.int16)
    got = nearest_pixels(words, 17, 11)
    assert got.dtype == torch.int16 and torch.equal(got, nearest_pixels(words.float(), 17, 11).to(torch.int16))


def test_resized_views_never_mix_depths_across_an_edge(setup):
    _, source = setup
    views = source.views(0, 0)
    depth = torch.full_like(views.depths, 3.0)
    depth[..., :20] = 1.0  # an edge, and pixels without depth
    depth[..., 0, 0], depth[..., 5, 5] = 0.0, float("nan")
    small = Views(views.images, views.cameras, depth).resized(16, 16)
    assert small.images.shape == (2, 3, 16, 16) and small.depths.shape == (2, 1, 16, 16)
    values = set(small.depths[small.depths == small.depths].unique().tolist())
    assert values <= {0.0, 1.0, 3.0} and {1.0, 3.0} <= values
    torch.testing.assert_close(small.cameras.K[:, :2], views.cameras.K[:, :2] / 3)
    torch.testing.assert_close(small.images.mean(), views.images.mean(), atol=2e-3, rtol=0)


@pytest.mark.parametrize("uint8", [False, True])
def test_views_rendered_at_half_size_come_back_at_the_image_size(setup, monkeypatch, uint8):
    cache, source = setup
    item = SceneDataset(source)[1]
    if uint8:
        item = {k: (v * 255).round().to(torch.uint8) if k in (LEFT, RIGHT) else v for k, v in item.items()}
    original = {k: v.clone() for k, v in item.items() if isinstance(v, torch.Tensor)}
    config = GenSplatConfig(probability=1.0, level="large", report=True)
    seen = sizes_rendered(monkeypatch)
    outs = {}
    for scale in (1.0, 0.5):
        torch.manual_seed(0)
        outs[scale] = GenSplatTransform(replace(config, render_scale=scale), cache)(item)
    assert seen == [(48, 48)] * 2 + [(24, 24)] * 2  # left and right, at each scale
    full, half = outs[1.0], outs[0.5]
    assert torch.equal(full["gensplat.theta_deg"], half["gensplat.theta_deg"])  # the same draws
    for key in (LEFT, RIGHT):
        assert half[key].shape == item[key].shape and half[key].dtype == item[key].dtype
        a, b = (x[key].float() / (255 if uint8 else 1) for x in (full, half))
        assert not torch.equal(a, b) and 20 < psnr(b, a) < math.inf
    assert all(torch.equal(item[k], v) for k, v in original.items())  # the input is untouched


def test_batch_path_at_a_scale_matches_the_worker(setup):
    cache, source = setup
    items = [SceneDataset(source)[i] for i in range(3)]
    config = GenSplatConfig(probability=1.0, level="large", render_scale=0.4, report=True)
    worker = GenSplatTransform(replace(config, render_in="worker"), cache)
    batch = GenSplatTransform(replace(config, render_in="batch"), cache)
    torch.manual_seed(3)
    expected = default_collate([worker(item) for item in items])
    torch.manual_seed(3)
    collated = default_collate([batch(item) for item in items])
    assert collated["gensplat.depth"].shape == (3, 1, 2, 19, 19)  # shipped at the render size
    got = render_batch(collated, batch)
    for key in (LEFT, RIGHT):
        assert got[key].shape == expected[key].shape
        torch.testing.assert_close(got[key], expected[key], atol=1e-5, rtol=0)


def test_gaussian_caches_render_at_the_scale(setup, tmp_path, monkeypatch):
    _, source = setup
    cache = SceneCache(tmp_path, StoredRGBD(), source.fingerprint)
    build_cache(cache, source, [0], progress=False)
    read = cache.read(0, 1, size=(24, 12))
    assert (read.cameras.width, read.cameras.height) == (24, 12)
    torch.testing.assert_close(read.cameras.K[:, 0], cache.read(0, 1).cameras.K[:, 0] / 2)
    torch.testing.assert_close(cache.read(0, 1, size=(48, 48)).cameras.K, cache.read(0, 1).cameras.K)
    seen = sizes_rendered(monkeypatch)
    item = SceneDataset(source)[1]
    out = GenSplatTransform(GenSplatConfig(probability=1.0, render_scale=0.25, replace=("left",)), cache)(item)
    assert seen == [(12, 12)] and out[LEFT].shape == item[LEFT].shape and out[LEFT].isfinite().all()


@pytest.mark.parametrize("render_in", ["worker", "batch"])
def test_a_one_pixel_render_stays_finite(setup, render_in):
    cache, source = setup
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, level="large", render_scale=1e-6, render_in=render_in),
                           cache)  # fmt: skip
    out = tf(SceneDataset(source)[2])
    if render_in == "batch":
        out = {k: v[0] for k, v in render_batch(default_collate([out]), tf).items() if isinstance(v, torch.Tensor)}
    assert out[LEFT].shape == (3, 48, 48) and out[LEFT].isfinite().all()
    assert render_size(48, 48, 1e-6) == (1, 1)


@pytest.mark.parametrize("scale", [0.0, -0.5, 1.5, float("nan")])
def test_render_scale_outside_zero_to_one_is_refused(scale):
    with pytest.raises(ValueError, match="render_scale must be in"):
        GenSplatConfig(render_scale=scale)
