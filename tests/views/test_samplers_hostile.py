"""The wider samplers and the focal-length change against hostile settings, values and poses."""

import json
import math

import numpy as np
import pytest
import torch

from gensplat_transforms.cache.builder import SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.cameras import FOCAL_MAX_PX, Cameras, look_at
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.rendering.output import render_view
from gensplat_transforms.settings import GenSplatConfig
from gensplat_transforms.views.perturbation import (
    FOCAL_SCALE_LIMITS,
    KEY_LIMIT,
    ROW,
    SAMPLERS,
    MixSampler,
    Moves,
    PaperSampler,
    Perturbation,
    PerturbationRange,
    TiltSampler,
    _move_rig,
    make_sampler,
    move_rig,
    perturb_pose,
    scale_focal,
)

F64 = torch.float64
RIG = torch.stack([look_at((1.05, 0.4, 0.5), (0.45, 0.0, 0.12)), look_at((1.05, -0.4, 0.5), (0.45, 0.0, 0.12))])
CAMS = Cameras.from_intrinsics(100.0, 90.0, 48.0, 40.0, RIG, 96, 80)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    """One cached reconstruction of the procedural scene (24x24) and the transform's settings."""
    source = SceneEpisodes(num_episodes=1, num_frames=1, size=24)
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(1), progress=False)
    return cache.read(0, 0, source.views(0, 0).images), GenSplatConfig()


def rigid_error(c2w: torch.Tensor) -> float:
    R = c2w[..., :3, :3].to(F64)
    return max(float((R.mT @ R - torch.eye(3, dtype=F64)).abs().max()), float((torch.linalg.det(R) - 1).abs().max()))


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: make_sampler("tilt", focal_scale="12"), r"^focal_scale must be \(low, high\), two numbers, got '12'"),
        (lambda: GenSplatConfig(focal_scale=(0.8,)), r"^focal_scale must be \(low, high\)"),
        (lambda: GenSplatConfig.from_dict({"focal_scale": None}), r"^focal_scale must be \(low, high\)"),
        (lambda: TiltSampler(10.0, focal_scale=(1.0, 1.0, 2.0)), r"^TiltSampler.focal_scale must be \(low, high\)"),
        (lambda: GenSplatConfig(tilt_deg="10"), r"^tilt_deg must be a number, got '10'"),
        (lambda: GenSplatConfig(shift_m=None), r"^shift_m must be a number, got None"),
        (lambda: GenSplatConfig(arc_deg=[45.0]), r"^arc_deg must be a number, got \[45.0\]"),
        (lambda: GenSplatConfig(seed=1.5), r"seed must be an integer, got 1.5"),
        (lambda: GenSplatConfig(seed="7"), r"seed must be an integer, got '7'"),
        (lambda: GenSplatConfig(views_per_source=math.nan), r"^GenSplatConfig.views_per_source must be an integer"),
        (lambda: GenSplatConfig(views_per_source="3"), r"^GenSplatConfig.views_per_source must be an integer"),
        (lambda: GenSplatConfig(views_per_source=True), r"^GenSplatConfig.views_per_source must be an integer"),
        (lambda: TiltSampler(10.0).sample(1.5), r"^TiltSampler.sample: episode_index must be an integer, got 1.5"),
        (lambda: Perturbation(shift_m="123"), r"^Perturbation.shift_m must be 3 numbers"),
        (lambda: Perturbation(focal_scale=True), r"^Perturbation.focal_scale must be a number, got True"),
        (lambda: PerturbationRange((1.0, 2.0, 3.0), (0.0, 0.0)), r"^PerturbationRange.theta_deg must be \(low, high\)"),
        (lambda: MixSampler(["paper"]), r"^MixSampler: samplers must be samplers .*, got \['str'\]"),
    ],
)
def test_settings_of_the_wrong_type_raise_type_errors_naming_them(make, match):
    with pytest.raises(TypeError, match=match):
        make()


@pytest.mark.parametrize("value", [3, 3.0, torch.tensor(3), np.int64(3)])
def test_an_integer_count_of_views_of_any_type_is_kept_as_a_python_int(value):
    config = GenSplatConfig(views_per_source=value)
    assert type(config.views_per_source) is int and config.views_per_source == 3
    assert GenSplatConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config


def test_ranges_too_wide_to_draw_from_are_refused_when_set():
    for make, match in [(lambda: TiltSampler(10.0, shift_m=1e308), r"^TiltSampler.shift_m must be at most"),
                        (lambda: make_sampler("arc", shift_m=1e308), r"^shift_m must be at most"),
                        (lambda: PerturbationRange((-1e308, 1e308), (0.0, 0.0), random_sign=False),
                         r"^PerturbationRange.theta_deg: need finite low <= high"),
                        (lambda: MixSampler(s for s in ()), "needs at least one sampler")]:  # fmt: skip
        with pytest.raises(ValueError, match=match):
            make()
    move = make_sampler("mix", shift_m=1e300, arc_deg=180.0, tilt_deg=180.0, focal_scale=FOCAL_SCALE_LIMITS).sample(3)
    assert all(math.isfinite(v) for v in move.as_row())


@pytest.mark.parametrize("scale", [1e307, 1e20, 1000.001, 9.99e-4, 1e-300, math.inf, math.nan])
def test_a_focal_change_beyond_the_limits_is_refused_by_the_move_the_sampler_and_the_batch_rows(scale):
    """Beyond a 1000x zoom either way a float32 projection overflows and the render would come
    back empty: the move, a sampler's range and scale_focal's rows all refuse it."""
    with pytest.raises(ValueError, match=r"^Perturbation.focal_scale must be a factor from 0.001 to 1000, got"):
        Perturbation(focal_scale=scale)
    if math.isfinite(scale):  # (a NaN or Inf range is refused as such)
        with pytest.raises(ValueError, match=r"^focal_scale: .* outside the focal-length factors 0.001 to 1000"):
            make_sampler("arc", focal_scale=sorted((scale, 1.0)))
    with pytest.raises(ValueError, match=r"^scale_focal: focal_scale .* outside the factors 0.001 to 1000"):
        scale_focal(CAMS.K, torch.tensor([1.0, scale], dtype=F64))


@pytest.mark.parametrize("limits", [FOCAL_SCALE_LIMITS, (3.0, 3.0), (5.0, 5.0), (0.9, 1.1)])
def test_drawn_focal_factors_stay_in_the_range_set_even_where_exp_of_log_rounds_past_it(limits):
    lo, hi = limits
    assert math.exp(math.log(3.0)) > 3.0 and math.exp(math.log(5.0)) < 5.0  # the rounding guarded against
    drawn = [make_sampler("tilt", focal_scale=limits).sample(i).focal_scale for i in range(300)]
    assert all(lo <= f <= hi for f in drawn)


def test_a_focal_change_out_of_the_dtypes_range_raises_instead_of_inf_focal_lengths():
    cameras = CAMS.to(dtype=torch.float16)  # fx 100 x 1000 is beyond float16's 65504
    with pytest.raises(ValueError, match=r"^scale_focal: focal_scale 1000.0 gives focal lengths .*torch.float16"):
        Perturbation(focal_scale=1e3).move(cameras, 0)


@pytest.mark.parametrize("scale", FOCAL_SCALE_LIMITS)
def test_a_render_at_the_focal_limits_is_finite_and_a_full_zoom_in_still_sees_the_scene(scale, scene):
    rec, config = scene
    out = render_view(rec, Perturbation(focal_scale=scale).move(rec.cameras, 0), config)
    assert all(bool(torch.isfinite(t).all()) for t in (out.rgb, out.alpha))
    if scale > 1:  # 1000x in: every pixel sees the scene
        assert float(out.alpha.min()) > 0.5
    else:  # 1000x out: the scene shrinks to a speck, still drawn
        assert 0 < float(out.alpha.mean()) < 0.1


def test_the_largest_zoom_of_the_longest_accepted_focal_length_still_renders_the_scene(scene):
    rec, config = scene
    cameras = rec.cameras

    def with_focal(focal: float) -> Cameras:
        K = cameras.K.clone()
        K[:, 0, 0] = K[:, 1, 1] = focal
        return Cameras(K, cameras.c2w, cameras.width, cameras.height)

    out = render_view(rec, Perturbation(focal_scale=FOCAL_SCALE_LIMITS[1]).move(with_focal(FOCAL_MAX_PX), 0), config)
    assert bool(torch.isfinite(out.rgb).all()) and float(out.alpha.min()) > 0.5
    with pytest.raises(ValueError, match=r"Cameras.K: focal lengths must be > 0 and at most 1e\+12 px"):
        with_focal(2 * FOCAL_MAX_PX)


@pytest.mark.parametrize(("theta", "dtype"), [(1e300, F64), (-1e200, F64), (2e4, torch.float16), (1e39, torch.float32)])
def test_any_finite_turn_gives_a_finite_rigid_pose(theta, dtype):
    cameras = CAMS.to(dtype=dtype)
    moved = Perturbation((0.3, -0.2, 0.9), theta, 0.01).move(cameras, 0).c2w
    same = Perturbation((0.3, -0.2, 0.9), math.fmod(theta, 360.0), 0.01).apply(cameras.c2w[:1], moved.new_zeros(3))
    assert torch.isfinite(moved).all() and rigid_error(moved) < (1e-6 if dtype == F64 else 8 * torch.finfo(dtype).eps)
    assert torch.equal(Perturbation((0.3, -0.2, 0.9), theta, 0.01).apply(cameras.c2w[:1], moved.new_zeros(3)), same)


def test_poses_that_are_not_rigid_float_transforms_or_moves_that_are_not_finite_are_refused():
    row = torch.tensor([Perturbation("x", 10.0, 0.01).as_row()], dtype=F64)
    with pytest.raises(TypeError, match=r"^perturb_pose: poses must be floating point, got torch.int64"):
        perturb_pose(torch.eye(4, dtype=torch.long), torch.zeros(3), "x", 10.0, 0.0)
    with pytest.raises(TypeError, match=r"^move_rig: poses must be floating point"):
        move_rig(RIG.long(), row, [0])
    scaled, mirrored, nan = RIG.clone(), RIG.clone(), RIG.clone()
    scaled[0, :3, :3] *= 1.01
    mirrored[0, :3, 0] *= -1
    nan[0, 0, 3] = math.nan
    for rig in (scaled, mirrored, nan):
        with pytest.raises(ValueError, match=r"^move_rig: the moved poses are not finite rigid transforms"):
            move_rig(rig, row, [0])
        with pytest.raises(ValueError, match=r"^perturb_pose: the moved poses are not finite rigid transforms"):
            Perturbation("x", 10.0).apply(rig[0], torch.zeros(3))
    with pytest.raises(ValueError, match=r"^move_rig: the moved poses are not finite rigid transforms"):
        move_rig(RIG, torch.full((1, ROW), math.nan, dtype=F64), [0])


def test_an_axis_of_tiny_or_huge_length_is_a_direction():
    assert Perturbation(axis=(1e-200, 0.0, 0.0)).axis == (1.0, 0.0, 0.0)
    assert Perturbation(axis=(1e200, -1e200, 0.0)).axis == pytest.approx((0.5**0.5, -(0.5**0.5), 0.0), abs=1e-15)


@pytest.mark.parametrize("dtype", [F64, torch.float32, torch.float16])
def test_a_batch_through_move_rig_is_perturbation_move_one_at_a_time(dtype):
    cameras = CAMS.to(dtype=dtype)
    top = KEY_LIMIT - 1  # the largest seed and indices a draw takes
    moves = [make_sampler(k, seed=top, focal_scale=(1e-3, 1e3), mode="frame").sample(top, top - 1, view=v)
             for k in SAMPLERS for v in range(2)]  # fmt: skip
    assert moves == [make_sampler(k, seed=top, focal_scale=(1e-3, 1e3), mode="frame").sample(top, top - 1, view=v)
                     for k in SAMPLERS for v in range(2)]  # fmt: skip
    rows = torch.tensor([m.as_row() for m in moves], dtype=F64).reshape(-1, 2, ROW)
    c2w = move_rig(cameras.c2w.expand(len(rows), 2, 4, 4), rows, [0, 1])
    K = scale_focal(cameras.K.expand(len(rows), 2, 3, 3), rows[..., 8])
    assert c2w.dtype == K.dtype == dtype and rigid_error(c2w) < (1e-6 if dtype == F64 else 8 * torch.finfo(dtype).eps)
    for i, move in enumerate(moves):
        one = move.move(cameras, i % 2)
        assert torch.equal(one.c2w[0], c2w[i // 2, i % 2]) and torch.equal(one.K[0], K[i // 2, i % 2])
        assert (one.width, one.height) == (96, 80) and torch.equal(one.K[0, :, 2], cameras.K[i % 2, :, 2])
    centre = RIG[0, :3, 3]
    assert torch.equal(perturb_pose(RIG[0], centre, "z", 30.0, 0.0)[:3, 3], centre)  # a pivot at the camera centre


def test_seeds_and_indices_from_2_to_the_32_are_refused_rather_than_drawn_like_smaller_ones():
    # NumPy splits a key integer into 32-bit words: (2**32, 5, 0, 1) would be the key (0, 1, 5, 0, 1)
    for make in (lambda: PaperSampler("large", seed=KEY_LIMIT), lambda: GenSplatConfig(seed=2**63),
                 lambda: PaperSampler("large").sample(KEY_LIMIT), lambda: TiltSampler(10.0).sample(0, view=2**40),
                 lambda: TiltSampler(10.0, mode="frame").sample(0, KEY_LIMIT)):  # fmt: skip
        with pytest.raises(ValueError, match=r"must be in \[0, 2\*\*32\)"):
            make()


def test_a_drawn_move_is_its_own_fields_again_and_a_focal_range_keeps_its_turn():
    plain, zoom = TiltSampler(10.0, seed=1), TiltSampler(10.0, seed=1, focal_scale=(0.8, 1.25))
    for ep in range(200):  # a unit axis is not normalised again (its last bits would change)
        move = plain.sample(ep)
        assert Perturbation(**move.as_dict()) == move and zoom.sample(ep).axis == move.axis


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_a_pivot_of_nearly_parallel_axes_is_found_in_float64_whatever_the_poses_dtype(dtype):
    # cameras 10 cm apart, each toed in 3 deg: axes cross 0.95 m out, where 1 - cos^2 of their angle is 1e-2
    rig = torch.stack([look_at((0.0, y, 0.0), (0.954, 0.0, 0.0)) for y in (0.05, -0.05)]).to(dtype)
    cameras = Cameras(CAMS.K.to(dtype), rig, 96, 80)
    move = Perturbation("z", 20.0, 0.02)
    moved = move.move(cameras, 0).c2w
    row = Moves.of_rows(torch.tensor([move.as_row()], dtype=F64))
    exact = _move_rig(rig.double(), row, [0])  # the same poses in float64
    assert moved.dtype == dtype and float((moved.double() - exact).abs().max()) < 8 * torch.finfo(dtype).eps


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_moved_half_precision_cameras_are_cameras_again_and_scaled_ones_are_not(dtype):
    cameras = CAMS.to(dtype=dtype)
    for seed in range(200):  # float16 rounds some moved rotations by more than RIGID_TOLERANCE
        moved = make_sampler("tilt", seed=seed).sample(0).move(cameras, seed % 2)
        assert Cameras(moved.K, moved.c2w, 96, 80).c2w.dtype == dtype
    scaled = CAMS.c2w.clone()
    scaled[0, :3, :3] *= 1.1
    with pytest.raises(ValueError, match=r"^Cameras.c2w: rotation is not orthonormal"):
        Cameras(CAMS.K.to(dtype), scaled.to(dtype), 96, 80)


@pytest.mark.parametrize("settings, match", [
    ({"shift_m": 1000.0}, r"GenSplatConfig.shift_m: a camera moves at most 1 m, got 1000"),
    ({"shift_m": 1e300}, r"GenSplatConfig.shift_m: a camera moves at most 1 m"),
    ({"level": PerturbationRange((0.0, 5.0), (0.5, 2.0))}, r"GenSplatConfig.level mu_m: a camera moves at most 1 m, got 2"),
    ({"pivot_depth": 1e300}, r"GenSplatConfig.pivot_depth: a positive distance in metres, at most 100"),
    ({"sampler": "arc", "pivot_depth": 1e6}, r"GenSplatConfig.pivot_depth: .* at most 100, got 1000000"),
    ({"views_per_source": 2**40}, r"GenSplatConfig.views_per_source must be in 1..1000, got 1099511627776"),
    ({"views_per_source": 10**20}, r"views_per_source must be in 1..1000"),
])  # fmt: skip
def test_move_settings_that_render_no_picture_are_refused(settings, match):
    """Shifts and pivots past what shows the scene, and view counts whose draws run out of keys:
    refused when set, not at the first training item."""
    with pytest.raises(ValueError, match=match):
        GenSplatConfig(**settings)
    edge = {"shift_m": 1.0, "level": PerturbationRange((0.0, 5.0), (-1.0, 1.0)), "pivot_depth": 100.0,
            "views_per_source": 1000}  # fmt: skip
    GenSplatConfig(**{k: edge[k] for k in settings if k in edge})  # the bounds themselves are taken


@pytest.mark.parametrize("settings", [{"cameras": ("left", "left")}, {"replace": ("right", "right")}])
def test_a_camera_named_twice_is_refused(settings):
    """A camera reconstructed (or replaced) twice was accepted: its Gaussians doubled, the pivot
    placed as if the camera were a pair."""
    with pytest.raises(ValueError, match=rf"GenSplatConfig.{next(iter(settings))} names \['\w+'\] more than once"):
        GenSplatConfig(**settings)
