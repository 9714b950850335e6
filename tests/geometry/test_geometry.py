"""The geometry path: model depth + RGB-D discs, calibrated or not, cached as depth."""

import json

import pytest
import torch
from safetensors.torch import save_file
from tiny_model import TINY, tiny_model

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import (
    RECONSTRUCTORS,
    GeometryReconstructor,
    RGBDReconstructor,
    Views,
    make_reconstructor,
)
from gensplat_transforms.geometry.model import ModelConfig


@pytest.fixture(scope="module")
def views():
    cams = default_cameras(64, 50)  # 64x50, not multiples of 14: the model runs at 70x56
    images, _ = TabletopScene(0).render(cams)
    return Views(images[:2], cams[:2])


def test_calibrated_views_give_depth_on_the_calibrated_cameras(views):
    rec = GeometryReconstructor(tiny_model())
    out = rec.predict_depth(views)
    assert out.images.shape == (2, 3, 56, 70) and out.depths.shape == (2, 1, 56, 70)
    assert (out.cameras.width, out.cameras.height) == (70, 56)
    torch.testing.assert_close(out.cameras.c2w, views.cameras.c2w)
    assert (out.depths > 0).all() and torch.isfinite(out.depths).all()
    g = rec(views)
    assert len(g.gaussians) == 2 * 56 * 70 and torch.equal(g.cameras.c2w, out.cameras.c2w)


def test_fit_scales_depth_with_the_calibrated_baseline_and_metric_does_not(views):
    far = views.cameras.with_c2w(views.cameras.c2w.clone())
    far.c2w[:, :3, 3] *= 2  # the same rig, twice the size
    wide = Views(views.images, far)
    fit, metric = GeometryReconstructor(tiny_model(), scale="fit"), GeometryReconstructor(tiny_model(), scale="metric")
    torch.testing.assert_close(fit.predict_depth(wide).depths, 2 * fit.predict_depth(views).depths, rtol=1e-4, atol=0)
    torch.testing.assert_close(metric.predict_depth(wide).depths, metric.predict_depth(views).depths)


def test_one_view_needs_a_metric_scale(views):
    one = Views(views.images[:1], views.cameras[:1])
    with pytest.raises(ValueError, match="two or more views"):
        GeometryReconstructor(tiny_model(), scale="fit").predict_depth(one)
    auto = GeometryReconstructor(tiny_model()).predict_depth(one)  # "auto" is metric here
    torch.testing.assert_close(auto.depths, GeometryReconstructor(tiny_model(), scale="metric").predict_depth(one).depths)


def test_uncalibrated_views_get_the_predicted_cameras(views):
    out = GeometryReconstructor(tiny_model()).predict_depth(Views(views.images))
    torch.testing.assert_close(out.cameras.c2w[0], torch.eye(4), atol=1e-5, rtol=0)  # first view = world
    assert (out.cameras.K[:, 0, 0] >= 1).all()


def test_confidence_masks_pixels(views):
    everything = GeometryReconstructor(tiny_model(), min_conf=0.0).predict_depth(views)
    nothing = GeometryReconstructor(tiny_model(), min_conf=1.0).predict_depth(views)
    assert (everything.depths > 0).all() and (nothing.depths == 0).all()
    assert len(GeometryReconstructor(tiny_model(), min_conf=1.0)(views).gaussians) == 0
    with pytest.raises(ValueError, match="min_conf"):
        GeometryReconstructor(tiny_model(), min_conf=2.0)
    with pytest.raises(ValueError, match="scale"):
        GeometryReconstructor(tiny_model(), scale="guess")


def test_identity_follows_weights_and_settings():
    a, b = GeometryReconstructor(tiny_model(seed=0)), GeometryReconstructor(tiny_model(seed=0))
    assert a.identity() == b.identity()
    assert a.identity() != GeometryReconstructor(tiny_model(seed=1)).identity()
    assert a.identity() != GeometryReconstructor(tiny_model(seed=0), min_conf=0.5).identity()


def test_a_pi3_checkpoint_directory_loads_by_path_and_through_the_registry(tmp_path, monkeypatch, views):
    """A Pi3 directory (its own config.json, no Gaussian head) builds the full configuration,
    swapped for the tiny one so the test stays small."""
    monkeypatch.setattr(ModelConfig, "full", classmethod(lambda cls: TINY))
    state = {k: v for k, v in tiny_model(seed=5).state_dict().items() if not k.startswith("gaussian_head.")}
    save_file(state, str(tmp_path / "model.safetensors"))
    (tmp_path / "config.json").write_text(json.dumps({"pos_type": "rope100", "decoder_size": "large"}))
    with pytest.warns(UserWarning, match="Pi3 checkpoint"):
        rec = make_reconstructor({"name": "geometry", "model": str(tmp_path), "options": {"scale": "fit"}})
    assert isinstance(rec, GeometryReconstructor) and rec.scale == "fit"
    assert rec.model.max_pixels == rec.max_pixels == 255_000  # Pi3's own loaders' limit
    assert torch.isfinite(rec(views).gaussians.means).all()
    with pytest.warns(UserWarning, match="Pi3 checkpoint"):
        auto = GeometryReconstructor(tmp_path)  # a Pi3 checkpoint is not metric: "auto" fits the scale
    assert not auto.metric
    torch.testing.assert_close(auto.predict_depth(views).depths, rec.predict_depth(views).depths)
    tiny_model(seed=5).save_pretrained(tmp_path / "ours")
    assert GeometryReconstructor(tmp_path / "ours").metric  # this project's checkpoints are metric


def test_registry_names_every_reconstructor():
    assert sorted(RECONSTRUCTORS) == ["gensplat", "geometry", "monocular", "rgbd"]
    assert isinstance(make_reconstructor({"name": "rgbd"}), RGBDReconstructor)
    with pytest.raises(ValueError, match="available"):
        make_reconstructor({"name": "nope"})


def test_geometry_cache_stores_depth_and_rebuilds_the_same_gaussians(tmp_path):
    source = SceneEpisodes(num_episodes=1, num_frames=2, size=42)
    rec = GeometryReconstructor(tiny_model())
    cache = SceneCache(tmp_path, rec, source.fingerprint)
    assert cache.kind == "depth"
    cache.ensure(0, source)
    for t in range(2):
        views = source.views(0, t)
        direct = rec(Views(views.images, views.cameras))
        cached = cache.read(0, t, views.images)
        assert torch.equal(cached.pixel_ids, direct.pixel_ids)
        # the depth codec's relative error bound (2.4e-4) carries over to the centres' distance from the camera
        scale = float(direct.gaussians.means.abs().max())
        torch.testing.assert_close(cached.gaussians.means, direct.gaussians.means, rtol=5e-4, atol=5e-4 * scale)


def test_frames_missing_from_a_stacked_item_come_from_the_source_at_the_cache_size(tmp_path):
    """The geometry cache is at the model's size (40 -> 42 px): frames the transform reads from
    the source (dataset size) are resized to it like the item's own images."""
    from gensplat_transforms.cache.builder import SceneDataset
    from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform

    source = SceneEpisodes(num_episodes=1, num_frames=2, size=40)
    cache = SceneCache(tmp_path, GeometryReconstructor(tiny_model()), source.fingerprint)
    cache.ensure(0, source)
    assert cache.image_size(0) == (42, 42)
    ds, left = SceneDataset(source), "observation.images.left"
    item = {**ds[1], left: torch.stack([ds[0][left], ds[1][left]])}  # only the left camera is stacked
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, replace=("left",), level="small"), cache, source)
    out = tf(item)[left]
    assert out.shape == (2, 3, 40, 40) and torch.isfinite(out).all()


@pytest.mark.parametrize("render_in", ["worker", "batch"])
def test_views_from_a_geometry_cache_keep_the_images_detail(tmp_path, render_in):
    """The cache holds depth at the model's 14x14, the frames are 56x56: the views are built and
    rendered at the frames' size from that depth, so an unmoved camera's view keeps its image's
    detail (each pixel's disc lands near it whatever the depth), where a render at the cache's
    size, resized, is blurred."""
    from torch.utils.data import default_collate

    from gensplat_transforms.cache.builder import SceneDataset
    from gensplat_transforms.core.metrics import psnr, sharpness_ratio
    from gensplat_transforms.rendering.batched import render_batch
    from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform, render_view

    source = SceneEpisodes(num_episodes=1, num_frames=1, size=56)
    cache = SceneCache(tmp_path, GeometryReconstructor(tiny_model(), max_pixels=196), source.fingerprint)
    cache.ensure(0, source)
    assert cache.image_size(0) == (14, 14)
    item, left = SceneDataset(source)[0], "observation.images.left"
    config = GenSplatConfig(probability=1.0, level="none", replace=("left",), render_in=render_in, backend="fast")
    transform = GenSplatTransform(config, cache)
    out = transform(item)
    if render_in == "batch":
        out = {k: v[0] for k, v in render_batch(default_collate([out]), transform).items()}
    assert out[left].shape == item[left].shape
    small = cache.read(0, 0, torch.nn.functional.interpolate(item[left][None].float(), size=(14, 14), mode="area")
                       .expand(2, -1, -1, -1))
    blurred = torch.nn.functional.interpolate(render_view(small, small.cameras[0:1], config).rgb,
                                              size=(56, 56), mode="bilinear")[0]
    truth = item[left].float()
    assert sharpness_ratio(out[left].float(), truth) > 0.6 and sharpness_ratio(blurred, truth) < 0.3
    assert psnr(out[left].float(), truth) > psnr(blurred, truth)


@pytest.mark.parametrize(("height", "width", "most"), [(480, 640, 255_000), (480, 640, 12_544), (720, 1280, 100_000),
                                                       (1, 5000, 196), (50, 64, 10**9)])  # fmt: skip
def test_model_size_keeps_the_aspect_within_max_pixels(height, width, most):
    from gensplat_transforms.geometry.feedforward import model_size

    h, w = model_size(height, width, most)
    assert h % 14 == 0 and w % 14 == 0 and h * w <= max(most, 196)
    if height * width > most and min(h, w) > 14:  # shrunk: the aspect kept to within a patch
        assert abs(w / h - width / height) <= 14 / min(h, w) * (1 + width / height)
        assert h * w > most * 0.8  # and not much smaller than the limit
    assert model_size(height, width) == model_size(height, width, None)


def test_max_pixels_shrinks_the_models_input_and_names_the_cache(views):
    """With max_pixels the model sees (and the depth comes at) the largest multiples of 14 within
    it; the identity names the limit, and without one stays what it was."""
    model = tiny_model()
    small = GeometryReconstructor(model, max_pixels=28 * 42)
    out = small.predict_depth(views)
    assert out.depths.shape == (2, 1, 28, 42) and (out.cameras.width, out.cameras.height) == (42, 28)
    assert torch.isfinite(out.depths).all() and len(small(views).gaussians) <= 2 * 28 * 42
    plain = GeometryReconstructor(model)
    assert "max_pixels" not in plain.config() and small.config()["max_pixels"] == 28 * 42
    assert small.identity() != plain.identity() == GeometryReconstructor(model, max_pixels=None).identity()
    assert GeometryReconstructor(model, max_pixels=10**6).predict_depth(views).depths.shape == (2, 1, 56, 70)
    from gensplat_transforms.geometry import GenSplatReconstructor

    g = GenSplatReconstructor(model, max_pixels=28 * 42).reconstruct(views)
    assert len(g.gaussians) == 2 * 28 * 42 and (g.cameras.width, g.cameras.height) == (64, 50)
    for bad in (0, 195, 1.5e5, True, "255000"):
        with pytest.raises(ValueError, match="max_pixels must be an integer >= 196"):
            GeometryReconstructor(model, max_pixels=bad)
        with pytest.raises(ValueError, match="max_pixels must be an integer >= 196"):
            GenSplatReconstructor(model, max_pixels=bad)
    spec = {"name": "geometry", "model": None, "options": {"max_pixels": 28 * 42}}
    assert make_reconstructor(spec).max_pixels == 28 * 42


def test_a_checkpoint_says_the_size_it_was_trained_at_and_the_geometry_path_keeps_to_it(tmp_path, views):
    """config.json's max_pixels: saved and loaded with the weights, the geometry path's
    default cap (an explicit one wins); the shipped model says 112x112; a bad value is
    refused naming the file."""
    from gensplat_transforms.geometry import GenSplatReconstructor
    from gensplat_transforms.geometry.model import GenSplatModel
    from gensplat_transforms.weights import DEFAULT_MODEL_DIR

    assert GenSplatModel.from_pretrained(DEFAULT_MODEL_DIR).max_pixels == 112 * 112
    model = tiny_model(seed=3)
    model.max_pixels = 28 * 42
    model.save_pretrained(tmp_path / "m")
    loaded = GenSplatModel.from_pretrained(tmp_path / "m")
    assert loaded.max_pixels == 28 * 42
    assert GeometryReconstructor(loaded).predict_depth(views).depths.shape == (2, 1, 28, 42)
    assert GeometryReconstructor(loaded).config()["max_pixels"] == 28 * 42
    assert GeometryReconstructor(loaded, max_pixels=10**6).predict_depth(views).depths.shape == (2, 1, 56, 70)
    assert GenSplatReconstructor(loaded).max_pixels is None  # the head keeps every pixel unless told
    meta = json.loads((tmp_path / "m" / "config.json").read_text())
    for bad in (100, 1.5e4, "12544"):
        (tmp_path / "m" / "config.json").write_text(json.dumps({**meta, "max_pixels": bad}))
        with pytest.raises(ValueError, match="config.json: max_pixels must be an integer >= 196"):
            GenSplatModel.from_pretrained(tmp_path / "m")
