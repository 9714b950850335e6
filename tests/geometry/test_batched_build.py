"""Cache builds run the geometry model on many timesteps at once (predict_depths, batch_timesteps)."""

import pytest
import torch
from tiny_model import tiny_model

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import GeometryReconstructor, RGBDReconstructor, Views
from gensplat_transforms.geometry.feedforward import INT_MAX, pixel_channels, timesteps_per_pass
from gensplat_transforms.geometry.model import GenSplatModel, ModelConfig
from gensplat_transforms.geometry.model.da3 import DA3Config, DepthAnything3


def timesteps(width: int, height: int, n: int = 5) -> list[Views]:
    """``n`` calibrated timesteps of two views, each of another scene."""
    cams = default_cameras(width, height)[:2]
    return [Views(TabletopScene(seed).render(cams)[0], cams) for seed in range(n)]


def counting(rec: GeometryReconstructor) -> list[int]:
    """The batch size of every forward pass of ``rec``'s model, as it happens."""
    sizes = []
    rec.model.register_forward_hook(lambda module, args, out: sizes.append(args[0].shape[0]))
    return sizes


@pytest.mark.parametrize("calibrated", [True, False], ids=["calibrated", "uncalibrated"])
@pytest.mark.parametrize("batch", [2, 5])
@pytest.mark.parametrize("kind", ["gensplat", "da3"])
def test_predict_depths_is_predict_depth_per_timestep(kind, batch, calibrated, request):
    """Each timestep's depth, cameras and images are predict_depth's, the model run ceil(5 / batch)
    times. "fit" scales each timestep by its own predicted baseline (the scenes differ)."""
    if kind == "gensplat":  # 64x50: the model runs at 70x56
        rec, views = GeometryReconstructor(tiny_model(), scale="fit", batch_timesteps=batch), timesteps(64, 50)
    else:
        rec, views = GeometryReconstructor(request.getfixturevalue("small"), batch_timesteps=batch), timesteps(42, 28)
    views = views if calibrated else [Views(v.images) for v in views]
    sizes = counting(rec)
    got = list(rec.predict_depths(views))
    assert sizes == [batch] * (5 // batch) + [5 % batch] * (5 % batch > 0)
    assert len(got) == 5
    for v, g in zip(views, got, strict=True):
        expected = rec.predict_depth(v)
        assert g.depths.shape == expected.depths.shape and (g.depths > 0).any()
        torch.testing.assert_close(g.depths, expected.depths, rtol=1e-5, atol=1e-7)
        torch.testing.assert_close(g.cameras.K, expected.cameras.K, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(g.cameras.c2w, expected.cameras.c2w, rtol=1e-5, atol=1e-5)
        assert torch.equal(g.images, expected.images)


def test_chunks_break_at_a_new_shape_or_camera_presence_and_read_lazily():
    rec = GeometryReconstructor(tiny_model(), batch_timesteps=4)
    first, other = timesteps(64, 50, 3), timesteps(42, 42, 2)
    views = [first[0], first[1], Views(first[2].images), *other]  # calibrated 2, uncalibrated 1, another size 2
    sizes, read = counting(rec), []

    def source():
        for v in views:
            read.append(v)
            yield v

    out = rec.predict_depths(source())
    first = next(out)
    assert len(read) == 3 and sizes == [2]  # the first chunk, and the view that ended it
    rest = [first, *out]
    assert sizes == [2, 1, 2] and len(rest) == 5
    for v, g in zip(views, rest, strict=True):
        torch.testing.assert_close(g.depths, rec.predict_depth(v).depths, rtol=1e-5, atol=1e-7)


def test_the_default_predict_depths_is_predict_depth_lazily():
    source = SceneEpisodes(num_episodes=1, num_frames=3, size=16)
    rec, read = RGBDReconstructor(), []

    def views():
        for t in range(3):
            read.append(t)
            yield source.views(0, t)

    out = rec.predict_depths(views())
    first = next(out)
    assert read == [0]
    for t, got in enumerate([first, *out]):
        assert torch.equal(got.depths, rec.predict_depth(source.views(0, t)).depths)


def test_a_batched_cache_build_stores_what_one_at_a_time_does(tmp_path):
    """Bit-identical on the CPU: the tiny model's depth does not depend on the batch here, so the
    log codes are the same (on CUDA, kernels chosen by batch size may move a depth by an ulp,
    and so a code by one 2**-11 step of log depth, 0.05 %)."""
    source = SceneEpisodes(num_episodes=1, num_frames=5, size=42)
    one, three = (GeometryReconstructor(tiny_model(), batch_timesteps=b) for b in (1, 3))
    assert one.identity() == three.identity()  # batching is no part of the cache's identity
    sizes = counting(three)
    caches = [SceneCache(tmp_path / name, rec, source.fingerprint) for name, rec in (("a", one), ("b", three))]
    for cache in caches:
        cache.ensure(0, source)
    assert sizes == [3, 2]
    for t in range(5):
        (da, ca), (db, cb) = (cache.read_depth(0, t) for cache in caches)
        assert (da > 0).any() and torch.equal(da, db)
        assert torch.equal(ca.K, cb.K) and torch.equal(ca.c2w, cb.c2w)


def test_automatic_batch_keeps_every_tensor_below_int_max():
    with torch.device("meta"):  # the full configuration's shapes, nothing allocated
        full = GenSplatModel(ModelConfig.full())
        base = DepthAnything3(DA3Config("da3-base"))
    cfg = full.config
    assert pixel_channels(full) == cfg.gs_features + cfg.gs_rgb_features == 288  # the Gaussian head at (H, W)
    assert pixel_channels(base) == 64  # DA3-Base's DPT head: 128 / 2 channels upsampled to (H, W)
    assert pixel_channels(tiny_model()) >= 8 + 8
    # the geometry path runs without the Gaussian head: the transformer's tokens are the widest
    assert pixel_channels(full, gaussians=False) == 126
    assert timesteps_per_pass(2, 294, 518, 126, "cuda") == 32

    b = timesteps_per_pass(2, 294, 518, 288, "cuda")  # 32 of these crashed the Gaussian head's upsampling
    assert b * 2 * 294 * 518 * 288 < INT_MAX <= (b + 1) * 2 * 294 * 518 * 288 and b == 24
    assert timesteps_per_pass(2, 182, 322, 288, "cuda") == 32  # DROID's size: the cap
    assert timesteps_per_pass(2, 182, 322, 288, torch.device("cuda", 1)) == 32
    assert timesteps_per_pass(2, 294, 518, 288, "cpu") == 1  # batching gains nothing on the CPU
    assert timesteps_per_pass(2, 294, 518, 288, "cpu", requested=64) == 24  # a given number is capped too
    assert timesteps_per_pass(2, 182, 322, 288, "cpu", requested=64) == 63
    assert timesteps_per_pass(2, 182, 322, 288, "cuda", requested=5) == 5
    assert timesteps_per_pass(8, 4200, 4200, 288, "cuda", requested=64) == 1  # never fewer than one

    rec = GeometryReconstructor(tiny_model())
    assert rec.timesteps_per_pass(2, 50, 64) == 1  # on the CPU
    huge = GeometryReconstructor(tiny_model(), batch_timesteps=10**9)
    fit = (INT_MAX - 1) // (2 * 56 * 70 * pixel_channels(huge.model, gaussians=False))  # at the model's 70x56
    assert huge.timesteps_per_pass(2, 50, 64) == fit > 1000


@pytest.mark.parametrize("bad", [0, -1, 2.5, "4", True])
def test_bad_batch_timesteps_are_refused(bad):
    with pytest.raises(ValueError, match="batch_timesteps"):
        GeometryReconstructor(tiny_model(), batch_timesteps=bad)


def test_the_geometry_path_runs_the_model_without_its_gaussian_head(monkeypatch):
    model = tiny_model()
    images = TabletopScene(seed=0).render(default_cameras(28, 28)[:2])[0]
    with torch.no_grad():
        full, geometry = model(images[None]), model(images[None], gaussians=False)
    assert set(geometry) == {"camera_poses", "local_points", "points", "conf"} < set(full)
    for key, value in geometry.items():
        assert torch.equal(value, full[key]), key

    def no_head(*args, **kwargs):
        raise AssertionError("the Gaussian head ran")

    monkeypatch.setattr(model.gaussian_head, "forward", no_head)
    rec = GeometryReconstructor(model)
    one = rec.predict_depth(Views(images))
    (batched,) = rec.predict_depths([Views(images)])
    assert torch.equal(one.depths, batched.depths) and (one.depths > 0).any()
    with pytest.raises(AssertionError, match="the Gaussian head ran"):
        model(images[None])
