"""An item passes through the transform, the plan, the reader and the renderer, each entered
once: the calls the transform's own code makes into the package's other modules during one
item, recorded with ``sys.setprofile``."""

import itertools
import sys
from collections import Counter

import pytest
import torch
from torch.utils.data import default_collate

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.rendering.scenes import render_scenes
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
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
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


STAGE_ORDER = ("core", "data", "calibration", "geometry", "cache", "views", "rendering", "settings", "transform")


def walk(fn) -> tuple[list[str], int]:
    """The walk of ``fn()`` through the stages, as docs/layout.md counts it: the functions of the
    stages above ``core`` (not dunders or dataclass-made methods) entered from another module,
    in call order and each once, and its climbs, the calls into a higher stage than the call
    before (counted over every such call)."""
    calls = []

    def profile(frame, event, arg):
        module, code = frame.f_globals.get("__name__", ""), frame.f_code
        if (event != "call" or not module.startswith("gensplat_transforms.") or code.co_name.startswith("__")
                or "<" in code.co_qualname or module.split(".")[1] == "core"):  # fmt: skip
            return
        if frame.f_back is not None and frame.f_back.f_globals.get("__name__") != module:
            calls.append((module, code.co_qualname))

    sys.setprofile(profile)
    try:
        fn()
    finally:
        sys.setprofile(None)
    stage = [STAGE_ORDER.index(m.split(".")[1]) for m, _ in calls]
    return [f"{m}.{q}" for m, q in dict.fromkeys(calls)], sum(b > a for a, b in itertools.pairwise(stage))


def test_a_batch_items_walk_is_short(setup):
    """The batch path renders through the worker's interfaces: its walk visits at most 14
    functions and climbs back up at most 4 times (the figures in docs/layout.md)."""
    cache, item = setup
    item = {k: v for k, v in item.items() if not k.endswith("_depth")}
    transform = GenSplatTransform(GenSplatConfig(probability=1.0, frame_offsets=(-1, 0), render_in="batch"), cache)
    batch = default_collate([transform(item), transform(item)])
    functions, climbs = walk(lambda: render_batch(batch, transform))
    assert len(functions) <= 14 and climbs <= 4, (len(functions), climbs, functions)
    assert f"{render_scenes.__module__}.render_scenes" in functions  # the worker's render


def test_a_worker_items_walk_does_not_grow(setup):
    """A worker item (a stack of two timesteps, with a depth cache, its episode file already
    open) visits at most 24 functions in 15 modules and climbs back up at most 5 times (the
    figures in docs/layout.md)."""
    cache, item = setup
    config = GenSplatConfig(probability=1.0, report=True, frame_offsets=(-1, 0), depth_unit="m")
    transform = GenSplatTransform(config, cache)
    transform(item)  # the episode file opened and kept: the walk of every later item
    functions, climbs = walk(lambda: transform(item))
    modules = set()
    for name in functions:  # the longest prefix that is a module
        while name not in sys.modules:
            name = name.rsplit(".", 1)[0]
        modules.add(name)
    assert len(functions) <= 24 and len(modules) <= 15 and climbs <= 5, (len(functions), len(modules), climbs, functions)
