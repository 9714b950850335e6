"""One plan per item: drawn once by the transform, replayed by transform(item, plan), and the
same moves in the worker path and the batch path (render_batch)."""

import numpy as np
import pytest
import torch
from torch.utils.data import default_collate

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform, render_view
from gensplat_transforms.views.perturbation import ROW, Perturbation, move_rig
from gensplat_transforms.views.plan import ViewPlan

LEFT, RIGHT = "observation.images.left", "observation.images.right"


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    source = SceneEpisodes(num_episodes=1, num_frames=3, size=24)
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(1), progress=False)
    return cache, SceneDataset(source)


def test_a_drawn_plan_replays_to_the_same_item_without_touching_the_rng(setup):
    cache, ds = setup
    tf = GenSplatTransform(GenSplatConfig(probability=0.5, report=True, level="large"), cache)
    item = ds[1]
    for seed in range(6):
        torch.manual_seed(seed)
        drawn = tf(item)
        torch.manual_seed(seed)
        plan = tf.plan(item)
        state = torch.get_rng_state()
        replayed = tf(item, plan)
        assert torch.equal(torch.get_rng_state(), state)  # a given plan draws nothing
        assert drawn.keys() == replayed.keys()
        assert all(torch.equal(drawn[k], replayed[k]) for k in drawn if isinstance(drawn[k], torch.Tensor))
        assert bool(replayed["gensplat.applied"].any()) == plan.applied


def test_a_chosen_view_is_one_of_the_drawn_ones(setup):
    """``plan(item, view)`` picks view ``view`` of the trajectory's ``views_per_source``: each
    one a draw can give, the views distinct, anything else refused."""
    cache, ds = setup
    tf = GenSplatTransform(GenSplatConfig(probability=1.0, level="large", views_per_source=3), cache)
    item = ds[1]
    chosen = [tf.plan(item, view) for view in range(3)]
    assert len({plan.rows for plan in chosen}) == 3
    drawn = set()
    for seed in range(40):
        torch.manual_seed(seed)
        drawn.add(tf.plan(item).rows)
    assert drawn == {plan.rows for plan in chosen}
    for bad in (3, -1, 1.0, True, np.True_, torch.tensor(True), np.int64(3), "1"):
        with pytest.raises(ValueError, match=r"view must be an integer in 0..2"):
            tf.plan(item, bad)
    for same in (np.int64(1), np.int32(1), torch.tensor(1)):  # any integer type is view 1
        assert tf.plan(item, same).rows == chosen[1].rows


def test_a_hand_made_plan_renders_its_moves_and_no_plan_keeps_the_images(setup):
    cache, ds = setup
    tf = GenSplatTransform(GenSplatConfig(report=True), cache)
    item = ds[2]
    moves = (Perturbation("x", 8.0, 0.03), Perturbation("y", -6.0, 0.0))
    out = tf(item, ViewPlan(True, moves))
    rec = cache.read(0, 2, ds.episodes.views(0, 2).images)
    for i, (key, p) in enumerate(zip((LEFT, RIGHT), moves)):
        want = render_view(rec, p.move(rec.cameras, i), tf.cfg).rgb[0]
        assert torch.equal(out[key], want.clamp(0, 1).to(out[key].dtype))
    assert out["gensplat.theta_deg"].tolist() == [8.0, -6.0] and out["gensplat.axis"].tolist() == [0, 1]
    kept = tf(item, ViewPlan(False, (Perturbation(), Perturbation())))
    assert torch.equal(kept[LEFT], item[LEFT]) and not kept["gensplat.applied"].any()
    with pytest.raises(ValueError, match="the plan moves 1 cameras, the config replaces"):
        tf(item, ViewPlan(True, moves[:1]))
    with pytest.raises(TypeError, match="plan must be a ViewPlan"):
        tf(item, {"applied": True})
    with pytest.raises(TypeError, match=r"moves must be Perturbations .* got \['str', 'float'\]"):
        ViewPlan(True, ("x", 5.0))
    with pytest.raises(TypeError, match="applied must be a bool"):
        ViewPlan(torch.tensor(True), moves)
    assert ViewPlan(True, list(moves)).moves == moves  # a list of moves becomes the plan's tuple


def test_the_batch_path_renders_the_plans_the_worker_path_renders(setup):
    cache, ds = setup
    config = {"probability": 1.0, "level": "large", "report": True}
    worker = GenSplatTransform(GenSplatConfig(**config, render_in="worker"), cache)
    batch = GenSplatTransform(GenSplatConfig(**config, render_in="batch"), cache)
    items = [ds[i] for i in range(3)]
    # (no exact zero angle: a camera moved straight forward sees fronto-parallel discs at equal
    # depths, whose order the two disc rules' round-off breaks differently)
    plans = [ViewPlan(True, (Perturbation("y", 4.0 + 3 * i, 0.01), Perturbation("x", -3.0, 0.02 * i))) for i in range(3)]
    expected = default_collate([worker(it, p) for it, p in zip(items, plans)])
    got = render_batch(default_collate([batch(it, p) for it, p in zip(items, plans)]), batch)
    for key in (LEFT, RIGHT):
        torch.testing.assert_close(got[key], expected[key], atol=2e-5, rtol=0)  # the two disc rules round apart by 1e-5


def test_move_rig_moves_any_batch_of_rigs_as_perturbation_move_moves_one(setup):
    cache, ds = setup
    cameras = cache.read(0, 0, ds.episodes.views(0, 0).images).cameras
    rigs = cameras.c2w.expand(5, 2, 4, 4)  # (5, V, 4, 4)
    for p in (Perturbation("y", 7.5, -0.02), Perturbation((0.3, -1.0, 0.2), 12.0, 0.01, (0.02, 0.0, -0.01), 1.2)):
        moves = torch.tensor([p.as_row()], dtype=torch.float64).expand(5, 1, ROW)
        moved = move_rig(rigs, moves, [1])
        assert moved.shape == (5, 1, 4, 4)
        for m in moved:
            assert torch.equal(m, p.move(cameras, 1).c2w)
    with pytest.raises(ValueError, match=rf"Moves: need \(\.\.\., {ROW}\) rows"):
        move_rig(rigs, torch.zeros(5, 1, 3, dtype=torch.float64), [1])


@pytest.mark.parametrize("sampler", [{"sampler": "tilt", "tilt_deg": 12.0, "shift_m": 0.03},
                                     {"sampler": "arc", "arc_deg": 40.0, "focal_scale": (0.8, 1.25)},
                                     {"sampler": "paper", "level": "medium", "focal_scale": (0.8, 0.9)}])  # fmt: skip
def test_the_wider_samplers_render_alike_in_the_worker_and_the_batch_path(setup, sampler):
    """Random-axis tilts with shifts, arcs about the vertical and focal-length changes: the
    batch path renders the plans the worker path renders, the images keep their size, and a
    changed focal length shows in the render (a hand-made zoom against the same move without)."""
    cache, ds = setup
    config = {"probability": 1.0, "report": True, **sampler}
    worker = GenSplatTransform(GenSplatConfig(**config, render_in="worker"), cache)
    batch = GenSplatTransform(GenSplatConfig(**config, render_in="batch"), cache)
    items = [ds[i] for i in range(3)]
    torch.manual_seed(0)
    plans = [worker.plan(it) for it in items]
    assert all(p.applied for p in plans)
    expected = default_collate([worker(it, p) for it, p in zip(items, plans)])
    got = render_batch(default_collate([batch(it, p) for it, p in zip(items, plans)]), batch)
    for key in (LEFT, RIGHT):
        assert got[key].shape == expected[key].shape == (3, 3, 24, 24)
        torch.testing.assert_close(got[key], expected[key], atol=1e-5, rtol=0)
    moves = expected["gensplat.move"]  # (3, R, ROW)
    if "focal_scale" in sampler:
        lo, hi = sampler["focal_scale"]
        assert bool(((moves[..., 8] >= lo - 1e-6) & (moves[..., 8] <= hi + 1e-6)).all())
    item = ds[1]
    base = Perturbation("x", 5.0, 0.01)
    zoomed = Perturbation("x", 5.0, 0.01, focal_scale=1.25)
    a, b = (worker(item, ViewPlan(True, (m, Perturbation()))) for m in (base, zoomed))
    assert (a[LEFT] - b[LEFT]).abs().mean() > 0.01 and torch.equal(a[RIGHT], b[RIGHT])
