"""Batch rendering (render_in="batch"): the same images as the worker path for the same draws,
on the CPU; the gsplat call's plumbing with a stand-in rasterizer. The LeRobot wiring is in
integrations/lerobot/test_batched_lerobot.py (skipped without the LeRobot extra, which these tests do not need)."""

from dataclasses import replace

import pytest
import torch
import torch.nn.functional as F
from helpers import assert_same_batch
from torch.utils.data import default_collate

from gensplat_transforms import render
from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.reader import disc_builder
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.cameras import Cameras, rigid_inverse
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.data.format import DepthSensor
from gensplat_transforms.geometry import Reconstructor, RGBDConfig, RGBDReconstructor, Views
from gensplat_transforms.rendering import gsplat_backend
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import BATCH_KEYS, GenSplatConfig, GenSplatTransform

LEFT, RIGHT = "observation.images.left", "observation.images.right"
IMAGES = (LEFT, RIGHT, "observation.images.front")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    source = SceneEpisodes(num_episodes=2, num_frames=4, size=32)
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(2), progress=False)
    return cache, SceneDataset(source)


def both_ways(cache, items: list[dict], seed: int, backend: str | None = None, device: str = "cpu",
              depth_sensors: dict | None = None, **config) -> tuple[dict, dict]:  # fmt: skip
    """The collated batch the worker path makes, and the batch path's rendering of its own
    collated batch (moved to ``device``, rendered there, back on the CPU), with torch seeded
    alike before each."""
    cfg = GenSplatConfig(**{"level": "large", "report": True, **config})
    worker = GenSplatTransform(replace(cfg, render_in="worker"), cache, depth_sensors=depth_sensors)
    batch = GenSplatTransform(replace(cfg, render_in="batch"), cache, depth_sensors=depth_sensors)
    torch.manual_seed(seed)
    expected = default_collate([worker(item) for item in items])
    torch.manual_seed(seed)
    collated = default_collate([batch(item) for item in items])
    assert set(BATCH_KEYS) <= set(collated)
    rendered = render_batch({k: v.to(device) for k, v in collated.items()}, batch, backend)
    return expected, {k: v.cpu() for k, v in rendered.items()}


def as_uint8(item: dict) -> dict:
    return {k: (v * 255).round().to(torch.uint8) if k in IMAGES else v for k, v in item.items()}


def test_float_images_at_probability_half_match_the_worker(setup):
    cache, ds = setup
    items = [ds[i] for i in range(8)]
    expected, got = both_ways(cache, items, seed=1, probability=0.5)
    applied = expected["gensplat.applied"][:, 0]
    assert applied.any() and not applied.all()  # some samples augmented, some kept
    assert_same_batch(expected, got, atol=1e-5)
    originals = torch.stack([item[LEFT] for item in items])
    assert torch.equal(got[LEFT][~applied], originals[~applied])
    assert (got[LEFT][applied] - originals[applied]).abs().amax((1, 2, 3)).min() > 0.1


def test_uint8_images_and_one_replaced_camera_match_the_worker(setup):
    cache, ds = setup
    items = [as_uint8(ds[i]) for i in range(4)]
    expected, got = both_ways(cache, items, seed=0, probability=1.0, replace=("right",), fill_holes=False,
                              background=(0.2, 0.4, 0.6))  # fmt: skip
    assert got[RIGHT].dtype == torch.uint8
    assert_same_batch(expected, got, atol=1)
    assert torch.equal(got[LEFT], torch.stack([item[LEFT] for item in items]))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(
    not torch.cuda.is_available(), reason="a CUDA batch needs a CUDA device"))])
def test_depth_holes_filled_before_the_discs_match_the_worker(tmp_path, device):
    """A cache of depth with sensor-like holes (a stored copy) and fill_depth_px: the batch path
    builds its discs from the same filled depth as the worker (on a CUDA batch too: the fill
    runs on the CPU and comes back)."""

    class Holed(SceneEpisodes):
        def views(self, episode, frame):
            views = super().views(episode, frame)
            depth = views.depths.clone()
            depth[..., 10:13, :] = 0  # a 3-row band without depth in every view
            return Views(views.images, views.cameras, depth)

    source = Holed(num_episodes=1, num_frames=2, size=32)
    cache = SceneCache(tmp_path, RGBDReconstructor(fill_depth_px=2), source.fingerprint)
    build_cache(cache, source, range(1), progress=False)
    assert not cache.read_depth(0, 0)[0][..., 11, :].any()  # stored as measured
    items = [SceneDataset(source)[i] for i in range(2)]
    expected, got = both_ways(cache, items, seed=0, backend="fast", device=device, probability=1.0)
    assert_same_batch(expected, got, atol=1e-4)
    unfilled = SceneCache(tmp_path / "plain", RGBDReconstructor(), source.fingerprint)
    build_cache(unfilled, source, range(1), progress=False)
    assert not torch.equal(both_ways(unfilled, items, seed=0, backend="fast", device=device,
                                     probability=1.0)[1][LEFT], got[LEFT])  # fmt: skip


def test_temporal_stacks_and_resized_images_match_the_worker(setup):
    cache, ds = setup
    resize = torch.nn.functional.interpolate

    def stacked(i: int) -> dict:  # frames i-1 and i of every camera, at 40x48 instead of the cache's 32x32
        item = ds[i]
        return {**item, **{k: resize(torch.stack([ds[i - 1][k], item[k]]), size=(40, 48)) for k in IMAGES}}

    items = [stacked(i) for i in (1, 3, 5, 7)]  # frames 1 and 3 of both episodes
    expected, got = both_ways(cache, items, seed=2, probability=1.0, views_per_source=2)
    assert got[LEFT].shape == (4, 2, 3, 40, 48)
    # the two disc rules round apart by 1e-5, which can swap the depth order of two saturated
    # discs on a pixel (measured: 0.005 on 0.015 % of the right camera's pixels)
    assert_same_batch(expected, got, atol=1e-2)
    for key in (LEFT, RIGHT):
        assert ((got[key] - expected[key]).abs() > 2e-5).float().mean() < 1e-3, key


def test_depth_smaller_than_the_render_travels_at_the_cache_size(setup):
    """Frames of 64x64 over a 32x32 cache: the workers ship the cached words (a quarter of the
    bytes), the batch side takes their pixels nearest the render's, as the worker path does."""
    cache, ds = setup
    big = [{k: torch.nn.functional.interpolate(v[None], size=(64, 64))[0] if k in IMAGES else v for k, v in ds[i].items()}
           for i in (0, 3, 6)]  # fmt: skip
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, render_in="batch"), cache)
    assert default_collate([tf(item) for item in big])["gensplat.depth"].shape == (3, 1, 2, 32, 32)
    half = GenSplatTransform(GenSplatConfig(probability=1.0, render_in="batch", render_scale=0.25), cache)
    assert half(big[0])["gensplat.depth"].shape == (1, 2, 16, 16)  # smaller than cached: shrunk in the worker
    expected, got = both_ways(cache, big, seed=4, probability=1.0)
    assert got[LEFT].shape == (3, 3, 64, 64)
    # 2x2 blocks of equal depth put a few discs on a threshold of the disc rule, which the
    # batch side runs in float64 and the worker compiled in float32 (measured: 0.005 on 0.02 %)
    assert_same_batch(expected, got, atol=1e-2)
    assert ((got[LEFT] - expected[LEFT]).abs() > 1e-5).float().mean() < 1e-3


def test_gaussians_caches_and_unlike_stacks_are_refused(setup, tmp_path):
    cache, ds = setup
    item = ds[1]
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, render_in="batch"), cache)
    with pytest.raises(ValueError, match="stacked alike"):
        tf({**item, LEFT: torch.stack([ds[0][LEFT], item[LEFT]])})
    gaussians = SceneCache(tmp_path, GaussiansOnly(), cache.dataset)
    with pytest.raises(ValueError, match="needs a depth cache"):
        GenSplatTransform(GenSplatConfig(probability=1.0, render_in="batch"), gaussians)
    with pytest.raises(TypeError, match="use render_in='worker'"):
        disc_builder(GaussiansOnly())
    with pytest.raises(ValueError, match="render_in"):
        GenSplatConfig(render_in="gpu")


class GaussiansOnly(Reconstructor):
    """A reconstructor whose cache stores Gaussians (it is no DepthReconstructor)."""

    name = "gaussians-only"

    def config(self) -> dict:
        return {}

    def reconstruct(self, views):
        raise AssertionError("never built here")


def fake_rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, near_plane, eps2d,
                       sh_degree, backgrounds, packed, render_mode):  # fmt: skip
    """gsplat's batched ``rasterization`` (scenes (M, N), cameras (M, C)) stood in for by the
    fast backend, one scene at a time: checks the arguments' layout and the outputs'."""
    assert means.shape[:-1] == opacities.shape and viewmats.shape[:2] == Ks.shape[:2] == backgrounds.shape[:2]
    assert render_mode in ("RGB", "RGB+ED") and not packed and eps2d == RGBDConfig().dilation
    rgbs, alphas = [], []
    for m in range(means.shape[0]):
        keep = opacities[m] > 0
        saturation = opacities[m][keep].clamp_min(1)  # the discs' opacity times their own saturation, exactly
        g = Gaussians(means[m][keep], quats[m][keep], scales[m][keep], opacities[m][keep] / saturation, colors[m][keep])
        cameras = Cameras(Ks[m].double(), rigid_inverse(viewmats[m].double()), width, height)
        out = render(g, cameras, background=backgrounds[m, 0], near=near_plane, sh_degree=sh_degree, backend="fast",
                     dilation=eps2d, saturation=saturation)  # fmt: skip
        channels = (out.rgb, out.depth) if render_mode == "RGB+ED" else (out.rgb,)  # expected depth sum(w z) / alpha
        rgbs.append(torch.cat(channels, 1).permute(0, 2, 3, 1))
        alphas.append(out.alpha.permute(0, 2, 3, 1))
    return torch.stack(rgbs), torch.stack(alphas), {}


def with_depth_maps(items: list[dict], ds, depth_maps: str | None) -> tuple[list[dict], dict]:
    """``items`` carrying the left camera's true depth map in millimetres ("camera"), or its
    depth sensor's own, a 40x30 map beside it ("sensor", the values stand in); and the
    ``depth_sensors`` to give the transform."""
    if not depth_maps:
        return items, {}
    items = [{**item, LEFT + "_depth": ds.episodes.render(int(item["episode_index"]), int(item["frame_index"]))[1][0]
              * 1000} for item in items]  # fmt: skip
    if depth_maps == "camera":
        return items, {}
    K = torch.tensor([[30.0, 0, 20], [0, 30, 15], [0, 0, 1]], dtype=torch.float64)
    to_camera = torch.eye(4, dtype=torch.float64)
    to_camera[0, 3] = -0.015
    sensor_maps = [F.interpolate(item[LEFT + "_depth"][None], size=(30, 40), mode="nearest")[0] for item in items]
    return [{**item, LEFT + "_depth": m} for item, m in zip(items, sensor_maps)], {"left": DepthSensor(K, 40, 30, to_camera)}


def assert_depth_maps_alike(items: list[dict], got: dict, expected: dict, edges: float = 0.0,
                            median_mm: float | None = None, max_mm: float | None = None) -> None:  # fmt: skip
    """The rendered depth maps moved, cover the same pixels as the worker's (all of them, or but
    for a share under ``edges``) and agree where both have depth: in the median to under
    ``median_mm``, at all but 1 pixel in 1000 to under ``max_mm`` (and there to under 20 times it)."""
    depth, worker = got[LEFT + "_depth"], expected[LEFT + "_depth"]
    assert depth.shape == worker.shape and depth.dtype == worker.dtype
    assert not torch.equal(depth, torch.stack([item[LEFT + "_depth"] for item in items]))
    apart = ((depth > 0) != (worker > 0)).float().mean()  # seen by one only: a pixel at an edge
    assert apart < edges if edges else apart == 0, f"{apart:.2%} of the pixels seen by one only"
    both = (depth > 0) & (worker > 0)
    error = (depth - worker)[both].abs()
    assert error.numel() > 0
    if median_mm is not None:
        assert error.median() < median_mm, f"median {error.median():.4f} mm"
    if max_mm is not None:  # at all but 1 pixel in 1000, where a round-off tips a faint disc in or out
        assert (error >= max_mm).float().mean() <= 1e-3 and error.max() < 20 * max_mm, f"max {error.max():.4f} mm"


@pytest.mark.parametrize(("render_scale", "depth_maps", "fill_holes"),
                         [(1.0, None, True), (0.5, None, True), (1.0, "camera", True), (1.0, "sensor", True),
                          (1.0, None, False)])  # fmt: skip
def test_the_single_gsplat_call_lays_out_scenes_and_cameras_as_the_worker(setup, monkeypatch, render_scale,
                                                                            depth_maps, fill_holes):  # fmt: skip
    """Also without hole filling, where the discs' ``cover`` shows partly covered pixels in their colour."""
    cache, ds = setup
    monkeypatch.setattr(gsplat_backend, "_rasterization", lambda: fake_rasterization)
    items, sensors = with_depth_maps([as_uint8(ds[i]) for i in (0, 2, 5, 6)], ds, depth_maps)
    expected, got = both_ways(cache, items, seed=0, backend="gsplat", depth_sensors=sensors, probability=1.0,
                              views_per_source=3, render_scale=render_scale, depth_unit="mm",
                              fill_holes=fill_holes)  # fmt: skip
    # the worker's images through gsplat's layout and float32 cameras, but for the disc rule's
    # round-off tipping a level (measured, float32 rule: one pixel of 12288 at render_scale 0.5)
    for key in (LEFT, RIGHT):
        diff = (got[key].float() - expected[key].float()).abs().amax(-3)  # (S, H, W): a pixel's channels
        assert diff.max() <= 1 and (diff > 0).float().mean() <= 1e-3, (key, diff.max(), (diff > 0).sum())
    # measured, float32 rule: 0.0081 mm (camera) at most; sensor: 0.117 mm at 1 pixel of 3949 (where
    # a softened disc's round-off decides whether a faint disc behind it still counts), else < 0.01 mm
    if depth_maps:
        assert_depth_maps_alike(items, got, expected, edges=0.0, max_mm=0.01)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="batch rendering with gsplat needs a CUDA device")
def test_on_cuda_one_gsplat_call_renders_the_worker_views(setup):
    pytest.importorskip("gsplat", reason="the gsplat package is not installed (optional extra)")
    cache, ds = setup
    items = [as_uint8(ds[i]) for i in range(8)]
    expected, got = both_ways(cache, items, seed=1, device="cuda", probability=0.5)
    for key in (LEFT, RIGHT):  # gsplat against the fast backend: 52.6 dB on the standard scene
        diff = (got[key].float() - expected[key].float()).abs()
        assert diff.mean() < 0.5 and (diff > 2).float().mean() < 0.01, key
    torch.testing.assert_close(got["gensplat.theta_deg"], expected["gensplat.theta_deg"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="batch rendering with gsplat needs a CUDA device")
@pytest.mark.parametrize("depth_maps", ["camera", "sensor"])
def test_on_cuda_gsplat_renders_depth_maps_as_the_worker(setup, depth_maps):
    """gsplat's expected depth (``RGB+ED``) for a camera's depth map and a depth sensor's."""
    pytest.importorskip("gsplat", reason="the gsplat package is not installed (optional extra)")
    cache, ds = setup
    items, sensors = with_depth_maps([as_uint8(ds[i]) for i in (0, 2, 5, 6)], ds, depth_maps)
    expected, got = both_ways(cache, items, seed=0, device="cuda", depth_sensors=sensors, probability=1.0,
                              depth_unit="mm")  # fmt: skip
    assert_depth_maps_alike(items, got, expected, edges=0.02, median_mm=2.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="a CUDA batch needs a CUDA device")
def test_on_cuda_a_named_backend_renders_scene_by_scene_on_the_batch_device(setup):
    """backend="reference" on a CUDA batch: no gsplat, every tensor stays on the batch's device."""
    cache, ds = setup
    items = [ds[i] for i in (0, 5)]
    expected, got = both_ways(cache, items, seed=3, backend="reference", device="cuda", probability=1.0)
    assert_same_batch(expected, got, atol=1e-4)


@pytest.mark.parametrize("sampler", ["paper", "tilt", "arc", "mix", "zoom"])
@pytest.mark.parametrize("depth_maps", [None, "camera", "sensor"])
def test_every_sampler_and_depth_setting_renders_the_worker_views(tmp_path, sampler, depth_maps):
    """One render path: with discs built by the same PyTorch rule on both sides (``fast=False``),
    the batch path's images and depth maps are the worker's to float round-off, for every
    sampler (a focal-length change: "zoom") and every kind of depth map."""
    source = SceneEpisodes(num_episodes=1, num_frames=4, size=24)
    cache = SceneCache(tmp_path, RGBDReconstructor(fast=False), source.fingerprint)
    build_cache(cache, source, range(1), progress=False)
    ds = SceneDataset(source)
    items, sensors = with_depth_maps([ds[i] for i in range(4)], ds, depth_maps)
    moves = {"sampler": "paper", "focal_scale": (0.8, 1.25)} if sampler == "zoom" else {"sampler": sampler}
    expected, got = both_ways(cache, items, seed=3, probability=1.0, depth_sensors=sensors, depth_unit="mm",
                              tilt_deg=8.0, arc_deg=20.0, **moves)  # fmt: skip
    depth_key = LEFT + "_depth"
    assert_same_batch({k: v for k, v in expected.items() if k != depth_key},
                      {k: v for k, v in got.items() if k != depth_key}, atol=1e-5)  # fmt: skip
    if depth_maps:  # millimetres at about 1 m: float32's round-off, relative
        torch.testing.assert_close(got[depth_key], expected[depth_key], atol=1e-4, rtol=2e-6)
    for key in (LEFT, RIGHT):  # every view was moved
        assert (got[key] - torch.stack([item[key] for item in items])).abs().amax((1, 2, 3)).min() > 0.01


def test_render_scenes_refuses_cameras_that_do_not_divide_among_the_scenes(setup):
    from gensplat_transforms.core.scenes import Scenes
    from gensplat_transforms.rendering.scenes import render_scenes

    cache, ds = setup
    rec = cache.read(0, 0, ds.episodes.views(0, 0).images)
    scenes = Scenes.of([rec, rec])
    with pytest.raises(ValueError, match="render_scenes: 2 scenes need B x C cameras"):
        render_scenes(scenes, rec.cameras[:1], GenSplatConfig())  # one camera for two scenes
    out = render_scenes(scenes, Cameras(rec.cameras.K.repeat(2, 1, 1), rec.cameras.c2w.repeat(2, 1, 1), 32, 32),
                        GenSplatConfig(), depth=True)  # fmt: skip
    assert out.rgb.shape == (2, 2, 3, 32, 32) and out.depth[0].shape == (2, 1, 32, 32)
    torch.testing.assert_close(out.rgb[0], out.rgb[1])  # one scene twice: the same views
