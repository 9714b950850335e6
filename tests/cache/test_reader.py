"""CacheReader: the transform's one way into a cache (an item's stacks of timesteps, a stack's
depth), checking the item's frame, clamping its stacks to the episode, building missing
episodes and keeping the storage's kind to itself."""

import pytest
import torch

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.reader import CacheReader
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.views import as_cache_images
from gensplat_transforms.geometry import GenSplatReconstructor, RGBDReconstructor
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform


@pytest.fixture(scope="module")
def source():
    return SceneEpisodes(num_episodes=2, num_frames=3, size=24)


@pytest.fixture(scope="module")
def depth_cache(source, tmp_path_factory):
    cache = SceneCache(tmp_path_factory.mktemp("depth"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(2), progress=False)
    return cache


def test_a_missing_episode_is_built_from_the_source_or_says_there_is_none(source, tmp_path):
    cache = SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)
    with pytest.raises(FileNotFoundError, match="episode 1 is missing .* no source was given"):
        CacheReader(cache).depth(1, 0, (0,), (8, 8), read=False)
    assert CacheReader(cache, source).depth(1, 2, (0,), (8, 8), read=False).words.shape == (1, 2, 8, 8)
    assert cache.status(1) == "ok"


def test_the_frame_is_checked_and_the_stacks_clamped_to_the_episode(source, depth_cache):
    reader = CacheReader(depth_cache)
    for frame in (3, -1):
        with pytest.raises(IndexError, match=f"frame_index {frame} outside episode 1 \\(0..2\\)"):
            reader.stacks(1, frame, [((0,), (8, 8))], lambda *args: None)
        with pytest.raises(IndexError, match=f"frame_index {frame} outside episode 1"):
            reader.depth(1, frame, (0,), (8, 8), read=False)  # checked even where nothing is read
    stack = reader.depth(1, 1, (-3, -1, 0, 2), (24, 24))  # frames 0, 0, 1, 2
    for k, f in enumerate((0, 0, 1, 2)):
        assert torch.equal(stack.words[k], depth_cache.read_depth_words(1, f)[0][0])


def test_each_timestep_is_read_once_and_images_asked_for_only_where_the_storage_rebuilds_from_them(
        source, depth_cache, tmp_path):  # fmt: skip
    asked = []

    def images(k, offset, frame, size):
        asked.append((k, offset, frame, size))
        return as_cache_images(source.views(0, frame).images, size[1], size[0])

    # two stacks (replaced cameras): frames 1, 2, 2 at 24x24 and 2, 0 at 12x12; each read once
    left, right = CacheReader(depth_cache).stacks(0, 1, [((0, 1, 5), (24, 24)), ((1, -1), (12, 12))], images)
    assert asked == [(0, 0, 1, (24, 24)), (1, 1, 2, (24, 24)), (1, -1, 0, (12, 12))]
    assert left[1] is left[2] is right[0] and left[0].gaussians.means.shape == (2 * 24 * 24, 3)
    assert right[1].gaussians.means.shape == (2 * 12 * 12, 3)
    reader = CacheReader(SceneCache(tmp_path, GenSplatReconstructor(), source.fingerprint), source)
    [found] = reader.stacks(0, 1, [((0,), (12, 12))], images)
    assert len(asked) == 3 and not reader.batchable  # stored Gaussians: never asked
    assert (found[0].cameras.width, found[0].cameras.height) == (12, 12)


def test_depth_at_the_render_size_or_the_stored_one_and_zeros_without_reading(depth_cache, monkeypatch):
    reader = CacheReader(depth_cache)
    stack = reader.depth(1, 1, (-1, 1), (12, 12))  # frames 0 and 2, smaller than stored: the nearest stored pixels
    (words, coded), cameras = depth_cache.read_depth_words(1, 2)
    assert stack.words.shape == (2, 2, 12, 12) and stack.words.dtype == torch.int16
    assert torch.equal(stack.words[1], words[..., 1::2, 1::2]) and stack.coded == coded
    assert torch.equal(stack.K[1], cameras.resize(12, 12).K) and torch.equal(stack.c2w[1], cameras.c2w)
    big = reader.depth(1, 2, (0,), (48, 48))  # larger: shipped at the stored size, cameras at the render's
    assert big.words.shape == (1, 2, 24, 24) and torch.equal(big.K[0], cameras.resize(48, 48).K)

    def no_read(*args):
        raise AssertionError("read")

    monkeypatch.setattr(depth_cache, "read_depth_words", no_read)
    empty = reader.depth(1, 1, (-1, 1), (12, 12), read=False)
    assert empty.words.shape == (2, 2, 12, 12) and not empty.words.any() and not empty.coded
    assert empty.K.shape == (2, 2, 3, 3) and not empty.c2w.any()


def test_a_gaussian_cache_cannot_serve_the_batch_path(source, tmp_path):
    cache = SceneCache(tmp_path, GenSplatReconstructor(), source.fingerprint)
    with pytest.raises(ValueError, match="stores Gaussians, not depth"):
        CacheReader(cache, source).depth(0, 0, (0,), (8, 8))
    with pytest.raises(ValueError, match=r"render_in='batch' needs a depth cache .* stores Gaussians"):
        GenSplatTransform(GenSplatConfig(render_in="batch"), cache, source)


def test_a_depth_cache_item_without_the_other_cameras_image_is_refused_by_name(source, depth_cache):
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, replace=("left",)), depth_cache)
    item = SceneDataset(source)[1]
    del item["observation.images.right"]
    with pytest.raises(KeyError, match=r"lacks camera image\(s\) \['observation.images.right'\]"):
        tf(item)
