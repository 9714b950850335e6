"""Issue 41: every mistake in the transform's items, model checkpoints, PLY files and preview
options gives a clear ValueError (a ``gensplat: error:`` line on the command line)."""

import pytest
import torch

from gensplat_transforms.cache import GaussianCache
from gensplat_transforms.episodes import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.reconstruction import RGBDReconstructor
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform

LEFT = "observation.images.left"


@pytest.fixture(scope="module")
def item_and_transform(tmp_path_factory):
    source = SceneEpisodes(num_episodes=2, num_frames=2, size=32)
    cache = GaussianCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(2), progress=False)
    return SceneDataset(source)[0], GenSplatTransform(GenSplatConfig(probability=1.0, level="small"), cache)


@pytest.mark.parametrize("value", [1.01, -0.01, None])
def test_float_images_beyond_zero_one_are_refused(item_and_transform, value):
    item, tf = item_and_transform
    image = item[LEFT] * 255  # None: a float image in [0, 255]
    if value is not None:
        image = item[LEFT].clone()
        image[0, 2, 5] = value
    with pytest.raises(ValueError, match=rf"{LEFT}: float images must be in \[0, 1\] \(or uint8"):
        tf({**item, LEFT: image})


def test_float_images_within_rounding_of_the_range_pass(item_and_transform):
    item, tf = item_and_transform
    assert tf({**item, LEFT: item[LEFT] * (1 + 1e-4)})[LEFT].shape == item[LEFT].shape


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_non_finite_pixels_are_refused(item_and_transform, value):
    item, tf = item_and_transform
    image = item[LEFT].clone()
    image[1, 3, 4] = value
    with pytest.raises(ValueError, match=f"{LEFT}: images must be finite"):
        tf({**item, LEFT: image})
    with pytest.raises(ValueError, match=f"{LEFT}: images must be finite"):
        tf({**item, LEFT: image.half()})


@pytest.mark.parametrize("key", ["episode_index", "frame_index"])
def test_fractional_indices_are_refused(item_and_transform, key):
    item, tf = item_and_transform
    for value in (torch.tensor(1.9), torch.tensor(0.5, dtype=torch.float64), 0.25, torch.tensor(float("nan"))):
        with pytest.raises(ValueError, match=f"{key} must be an integer"):
            tf({**item, key: value})
    assert tf({**item, key: torch.tensor(0.0)})[LEFT].shape == item[LEFT].shape
