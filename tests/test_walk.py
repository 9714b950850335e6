"""An item passes through the transform, the plan, the reader and the renderer, each entered
once: the calls the transform's own code makes into the package's other modules during one
item, recorded with ``sys.setprofile``."""

import sys
from collections import Counter

import pytest
import torch

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import GaussianCache
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform
from gensplat_transforms.views.perturbation import Perturbation
from gensplat_transforms.views.plan import ViewPlan

LEFT, RIGHT = "observation.images.left", "observation.images.right"
TRANSFORM = GenSplatTransform.__module__
STAGES = {"gensplat_transforms.views.plan": "plan", "gensplat_transforms.cache.reader": "reader",
          "gensplat_transforms.rendering.output": "renderer"}  # fmt: skip


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    source = SceneEpisodes(num_episodes=1, num_frames=3, size=16)
    cache = GaussianCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(1), progress=False)
    ds = SceneDataset(source)
    depth = source.render(0, 2)[1]
    item = {**ds[2], LEFT: torch.stack([ds[1][LEFT], ds[2][LEFT]]), RIGHT: torch.stack([ds[1][RIGHT], ds[2][RIGHT]]),
            LEFT + "_depth": torch.stack([depth[0], depth[0]])}  # fmt: skip
    return cache, item


def entered(transform: GenSplatTransform, item: dict, plan: ViewPlan | None = None) -> list[str]:
    """The package's modules (other than transform.py) that ``transform(item, plan)`` calls
    into from its own code, in call order: calls whose callers, up to ``__call__``, are all
    transform.py's (the reader calling back for the item's images does not count)."""
    top, calls = GenSplatTransform.__call__.__code__, []

    def profile(frame, event, arg):
        module = frame.f_globals.get("__name__", "")
        if event != "call" or not module.startswith("gensplat_transforms.") or module == TRANSFORM:
            return
        caller = frame.f_back
        while caller is not None and caller.f_globals.get("__name__") == TRANSFORM:
            if caller.f_code is top:
                calls.append(module)
                return
            caller = caller.f_back

    sys.setprofile(profile)
    try:
        transform(item, plan)
    finally:
        sys.setprofile(None)
    return calls


def stages(calls: list[str]) -> list[str]:
    return [STAGES[m] for m in calls if m in STAGES]


def test_the_worker_path_enters_the_plan_the_reader_and_the_renderer_once(setup):
    cache, item = setup
    config = GenSplatConfig(probability=1.0, report=True, frame_offsets=(-1, 0), depth_unit="m")
    calls = entered(GenSplatTransform(config, cache), item)
    assert stages(calls) == ["plan", "reader", "renderer"], Counter(calls)
    plan = ViewPlan(True, (Perturbation("x", 5.0, 0.0), Perturbation("y", 3.0, 0.01)))
    assert stages(entered(GenSplatTransform(config, cache), item, plan)) == ["reader", "renderer"]  # replayed


def test_the_batch_path_enters_the_reader_once_and_never_the_renderer(setup):
    cache, item = setup
    item = {k: v for k, v in item.items() if not k.endswith("_depth")}
    config = GenSplatConfig(probability=1.0, report=True, frame_offsets=(-1, 0), render_in="batch")
    calls = entered(GenSplatTransform(config, cache), item)
    assert stages(calls) == ["plan", "reader"], Counter(calls)
