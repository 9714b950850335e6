"""Tests for gensplat_transforms.views.perturbation (the paper's pivot-and-push camera protocol)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import torch

from gensplat_transforms.core.cameras import Cameras, look_at
from gensplat_transforms.views.perturbation import (
    AXES,
    EVAL_LEVELS,
    LEVELS,
    ROW,
    ArcSampler,
    Moves,
    PaperSampler,
    Perturbation,
    PerturbationRange,
    TiltSampler,
    axis_rotation,
    closest_points_between_axes,
    get_range,
    make_sampler,
    move_rig,
    perturb_pose,
    pivot_point,
)

DTYPE = torch.float64


def random_pose(g: torch.Generator) -> torch.Tensor:
    """A random rigid OpenCV camera-to-world (4, 4)."""
    q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=DTYPE))
    R = q * torch.sign(torch.diagonal(r))
    if torch.linalg.det(R) < 0:
        R[:, 0] = -R[:, 0]
    c2w = torch.eye(4, dtype=DTYPE)
    c2w[:3, :3], c2w[:3, 3] = R, torch.randn(3, generator=g, dtype=DTYPE)
    return c2w


def camera_coords(c2w: torch.Tensor, p: torch.Tensor) -> torch.Tensor:
    """World point p in the camera frame of c2w."""
    return c2w[:3, :3].T @ (p - c2w[:3, 3])


def inside_image(uv: torch.Tensor, width: int, height: int) -> torch.Tensor:
    return (uv[..., 0] >= 0) & (uv[..., 0] < width) & (uv[..., 1] >= 0) & (uv[..., 1] < height)


# ---------------------------------------------------------------------------- real DROID rig
def test_droid_optical_axes_pass_within_a_few_millimetres(droid):
    a, b = droid.cameras.c2w
    pa, pb = closest_points_between_axes(a, b)
    gap = float((pa - pb).norm())
    print(f"DROID optical axes closest approach: {gap * 1000:.2f} mm")
    assert gap < 0.01
    # it really is the closest approach: the connecting segment is perpendicular to both axes
    for c2w, p in ((a, pa), (b, pb)):
        assert abs(float((pa - pb) @ c2w[:3, 2])) < 1e-12
        # and the point lies on that camera's axis
        torch.testing.assert_close(
            torch.linalg.cross(p - c2w[:3, 3], c2w[:3, 2]), torch.zeros(3, dtype=DTYPE)
        )
    # brute force over a grid of axis parameters cannot beat it
    s = torch.linspace(-2.0, 2.0, 401, dtype=DTYPE)
    la = a[:3, 3] + s[:, None] * a[:3, 2]
    lb = b[:3, 3] + s[:, None] * b[:3, 2]
    assert torch.cdist(la, lb).min() >= gap - 1e-12


def test_droid_pivot_lies_in_front_of_both_cameras(droid):
    cams = droid.cameras
    pivot = pivot_point(cams.c2w[0], cams.c2w[1])
    uv, depth = cams.project(pivot[None])
    print(f"DROID pivot {pivot.tolist()}, depth in each camera {depth[:, 0].tolist()} m")
    assert (depth > 0).all()
    assert (depth < 3.0).all()  # a tabletop rig: the workspace is within arm's reach
    assert inside_image(uv, droid.width, droid.height).all()


def _large_perturbations() -> list[Perturbation]:
    """Seeded Large samples over both axes plus the extreme corners of the Large range."""
    out = [PaperSampler("large", seed=seed).sample(ep) for seed in range(3) for ep in range(100)]
    lo, hi = LEVELS["large"].theta_deg
    m_lo, m_hi = LEVELS["large"].mu_m
    out += [
        Perturbation(axis, sign * theta, mu)
        for axis in ("x", "y")
        for sign in (1, -1)
        for theta in (lo, hi)
        for mu in (m_lo, m_hi)
    ]
    return out


def test_droid_pivot_stays_in_the_image_after_large_perturbations(droid):
    cams = droid.cameras
    pivot = pivot_point(cams.c2w[0], cams.c2w[1])
    perts = _large_perturbations()
    assert {(p.axis, p.theta_deg > 0) for p in perts} == {(a, pos) for a in "xy" for pos in (True, False)}
    assert any(abs(p.theta_deg) == 30.0 and p.mu_m == 0.06 for p in perts)
    c2w = torch.stack([p.apply(cams.c2w, pivot) for p in perts]).reshape(-1, 4, 4)  # (P * 2, 4, 4)
    moved = Cameras(cams.K.repeat(len(perts), 1, 1), c2w, droid.width, droid.height)
    uv, depth = moved.project(pivot[None].expand(len(moved), 1, 3))
    assert (depth > 0).all()
    assert inside_image(uv, droid.width, droid.height).all()
    # why: rotating about the pivot leaves its camera coordinates unchanged, and the push only
    # brings it mu closer along the optical axis
    before = torch.stack([camera_coords(c, pivot) for c in cams.c2w]).repeat(len(perts), 1)
    after = torch.stack([camera_coords(c, pivot) for c in c2w])
    mu = torch.tensor([p.mu_m for p in perts for _ in range(2)], dtype=DTYPE)
    torch.testing.assert_close(after[:, :2], before[:, :2])
    torch.testing.assert_close(after[:, 2], before[:, 2] - mu)


# ---------------------------------------------------------------------------- pivot
def test_pivot_of_cameras_looking_at_a_common_point():
    target = torch.tensor([0.3, -0.2, 0.1], dtype=DTYPE)
    a, b = look_at((1.0, 0.5, 0.8), target), look_at((-0.6, 0.9, 0.4), target)
    torch.testing.assert_close(pivot_point(a, b), target)


def test_pivot_of_skew_axes():
    a = look_at((-1.0, 0.0, 0.0), (0.0, 0.0, 0.0))  # the world x axis
    b = look_at((0.0, -1.0, 0.2), (0.0, 0.0, 0.2))  # parallel to y, 0.2 m higher
    pa, pb = closest_points_between_axes(a, b)
    torch.testing.assert_close(pa, torch.tensor([0.0, 0.0, 0.0], dtype=DTYPE))
    torch.testing.assert_close(pb, torch.tensor([0.0, 0.0, 0.2], dtype=DTYPE))
    torch.testing.assert_close(pivot_point(a, b), torch.tensor([0.0, 0.0, 0.1], dtype=DTYPE))
    torch.testing.assert_close(pivot_point(b, a), pivot_point(a, b))


@pytest.mark.parametrize("direction", [1.0, -1.0])  # parallel and anti-parallel axes
def test_pivot_falls_back_to_the_midpoint_of_centres_for_parallel_axes(direction):
    a = look_at((0.0, 0.0, 0.0), (1.0, 0.0, 0.0))
    b = look_at((0.0, 0.4, 0.2), (direction, 0.4, 0.2))
    assert closest_points_between_axes(a, b) is None
    torch.testing.assert_close(pivot_point(a, b), torch.tensor([0.0, 0.2, 0.1], dtype=DTYPE))


# ---------------------------------------------------------------------------- perturb_pose
@pytest.mark.parametrize(("axis", "src", "dst"), [("x", 1, 2), ("y", 2, 0)])
def test_axis_rotation_is_right_handed(axis, src, dst):
    R = axis_rotation(axis, 90.0)
    e = torch.eye(3, dtype=DTYPE)
    torch.testing.assert_close(R @ e[src], e[dst])  # x: y -> z, y: z -> x
    torch.testing.assert_close(R.T @ R, e)


def test_rotation_about_pivot_preserves_distance_and_moves_orientation():
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        c2w, pivot = random_pose(g), torch.randn(3, generator=g, dtype=DTYPE)
        theta = float(torch.empty(1).uniform_(-60, 60, generator=g))
        for axis in ("x", "y"):
            out = perturb_pose(c2w, pivot, axis, theta, 0.0)
            Ra = axis_rotation(axis, theta)
            assert float((out[:3, 3] - pivot).norm()) == pytest.approx(
                float((c2w[:3, 3] - pivot).norm()), abs=1e-12
            )
            torch.testing.assert_close(out[:3, :3], Ra @ c2w[:3, :3])
            torch.testing.assert_close(out[:3, 3] - pivot, Ra @ (c2w[:3, 3] - pivot))
            torch.testing.assert_close(out[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=DTYPE))
            # the world rotation axis is fixed: the centre's coordinate along it does not change
            k = "xyz".index(axis)
            assert float(out[k, 3]) == pytest.approx(float(c2w[k, 3]), abs=1e-12)


@pytest.mark.parametrize(("axis", "theta", "mu"), [("x", 17.0, 0.05), ("y", -30.0, 0.06), ("y", 0.0, 0.02)])
def test_forward_move_is_exactly_mu_along_the_new_viewing_axis(axis, theta, mu):
    c2w, pivot = random_pose(torch.Generator().manual_seed(1)), torch.tensor([0.1, 0.2, 0.3], dtype=DTYPE)
    rotated = perturb_pose(c2w, pivot, axis, theta, 0.0)
    pushed = perturb_pose(c2w, pivot, axis, theta, mu)
    torch.testing.assert_close(pushed[:3, :3], rotated[:3, :3])
    torch.testing.assert_close(pushed[:3, 3] - rotated[:3, 3], mu * pushed[:3, 2])
    assert float((pushed[:3, 3] - rotated[:3, 3]).norm()) == pytest.approx(mu, abs=1e-12)
    # a point on the old optical axis in front of the camera gets mu closer
    p = rotated[:3, 3] + 0.7 * rotated[:3, 2]
    assert float(camera_coords(pushed, p)[2]) == pytest.approx(0.7 - mu, abs=1e-12)


def test_identity_perturbation():
    c2w, pivot = random_pose(torch.Generator().manual_seed(2)), torch.tensor([0.3, -0.1, 0.5], dtype=DTYPE)
    for axis in ("x", "y"):
        torch.testing.assert_close(perturb_pose(c2w, pivot, axis, 0.0, 0.0), c2w, rtol=0, atol=1e-15)
    assert Perturbation().is_identity and not Perturbation("x", 1.0, 0.0).is_identity
    torch.testing.assert_close(Perturbation("x").apply(c2w, pivot), c2w, rtol=0, atol=1e-15)


def test_batched_and_float32_poses():
    g = torch.Generator().manual_seed(3)
    c2w = torch.stack([random_pose(g) for _ in range(4)])
    pivot = torch.tensor([0.0, 0.1, 0.2], dtype=DTYPE)
    p = Perturbation("x", 12.0, 0.03)
    batched = p.apply(c2w, pivot)
    assert batched.shape == (4, 4, 4)
    for i in range(4):
        torch.testing.assert_close(batched[i], p.apply(c2w[i], pivot))
    out32 = p.apply(c2w.float(), pivot.tolist())
    assert out32.dtype == torch.float32
    torch.testing.assert_close(out32.double(), batched, atol=1e-5, rtol=0)
    assert p.as_dict() == {"axis": "x", "theta_deg": 12.0, "mu_m": 0.03}


# ---------------------------------------------------------------------------- levels & sampler
def test_levels_match_the_paper():
    assert EVAL_LEVELS == ("none", "small", "medium", "large", "extreme")
    expected = {
        "none": ((0, 0), (0, 0), True),
        "small": ((3, 6), (0.005, 0.02), True),
        "medium": ((8, 15), (0.02, 0.04), True),
        "large": ((18, 30), (0.04, 0.06), True),
        "extreme": ((60, 60), (0.12, 0.12), True),
        "train": ((-30, 30), (0.005, 0.06), False),
    }
    assert {k: (v.theta_deg, v.mu_m, v.random_sign) for k, v in LEVELS.items()} == expected
    assert get_range("large") is LEVELS["large"]
    custom = PerturbationRange((1.0, 2.0), (0.0, 0.01))
    assert get_range(custom) is custom


@pytest.mark.parametrize("level", sorted(LEVELS))
def test_samples_stay_within_the_level_range(level):
    rng = LEVELS[level]
    samples = [PaperSampler(level, seed=7).sample(ep) for ep in range(300)]
    thetas = torch.tensor([s.theta_deg for s in samples], dtype=DTYPE)
    mus = torch.tensor([s.mu_m for s in samples], dtype=DTYPE)
    lo, hi = rng.theta_deg
    magnitude = thetas.abs() if rng.random_sign else thetas
    assert ((magnitude >= lo) & (magnitude <= hi)).all()
    assert ((mus >= rng.mu_m[0]) & (mus <= rng.mu_m[1])).all()
    assert {s.axis for s in samples} == {"x", "y"}
    if hi > 0:  # both signs occur (a magnitude range with a random sign, or [-30, 30])
        assert (thetas > 0).any() and (thetas < 0).any()
    if hi > lo:  # values spread over the range rather than sticking to one end
        span = float(magnitude.max() - magnitude.min())
        assert span > 0.8 * (hi - lo)


def test_train_level_draws_signed_angles_directly():
    samples = [PaperSampler("train", seed=0).sample(ep) for ep in range(400)]
    thetas = torch.tensor([s.theta_deg for s in samples])
    assert thetas.min() >= -30 and thetas.max() <= 30
    assert (thetas.abs() < 3).any()  # small angles occur: it is not a magnitude range mirrored


def test_episode_mode_shares_one_perturbation_per_episode():
    s = PaperSampler("large", mode="episode", seed=0)
    for ep in range(5):
        first = s.sample(ep, 0)
        assert all(s.sample(ep, frame) == first for frame in range(1, 50))
    assert len({s.sample(ep) for ep in range(20)}) == 20  # episodes differ


def test_frame_mode_differs_per_frame_but_is_repeatable():
    s = PaperSampler("large", mode="frame", seed=0)
    frames = [s.sample(3, frame) for frame in range(50)]
    assert len(set(frames)) == 50
    assert [s.sample(3, frame) for frame in range(50)] == frames


def test_views_give_different_perturbations_of_the_same_episode():
    s = PaperSampler("train", seed=0)
    views = [s.sample(0, view=v) for v in range(3)]
    assert len(set(views)) == 3
    assert s.sample(0, view=1) == views[1]


def test_seeding_is_deterministic_and_seeds_differ():
    a, b, c = (PaperSampler("medium", seed=s) for s in (11, 11, 12))
    seq = [a.sample(ep, view=v) for ep in range(10) for v in range(2)]
    assert seq == [b.sample(ep, view=v) for ep in range(10) for v in range(2)]
    assert seq != [c.sample(ep, view=v) for ep in range(10) for v in range(2)]
    # the sampler survives pickling (DataLoader workers are spawned) with the same stream
    d = pickle.loads(pickle.dumps(a))
    assert [d.sample(ep, view=v) for ep in range(10) for v in range(2)] == seq


def test_single_axis_sampler():
    s = PaperSampler("small", axes=("x",), seed=0)
    assert {s.sample(ep).axis for ep in range(50)} == {"x"}


def test_none_and_extreme_levels_are_fixed():
    assert PaperSampler("none").sample(4).is_identity
    e = PaperSampler("extreme").sample(4)
    assert abs(e.theta_deg) == 60.0 and e.mu_m == 0.12


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: PaperSampler("huge"), "unknown perturbation level 'huge'; choose one of"),
        (lambda: get_range("Large "), "unknown perturbation level"),
        (lambda: PaperSampler("large", mode="step"), "mode must be 'episode' or 'frame', got 'step'"),
        (lambda: PaperSampler("large", axes=("z",)), "axes must be a non-empty subset"),
        (lambda: PaperSampler("large", axes=()), "axes must be a non-empty subset"),
        (lambda: PaperSampler("large", seed=-1), r"seed must be in \[0, 2\*\*32\), got -1"),
        (lambda: PaperSampler("large").sample(-1), r"indices must be in \[0, 2\*\*32\)"),
        (lambda: PaperSampler("large", mode="frame").sample(0, -2), r"indices must be in \[0, 2\*\*32\)"),
        (lambda: Perturbation(axis="w"), "axis must be one of"),
        (lambda: Perturbation(axis=(0.0, 0.0, 0.0)), "a direction needs 3 finite values, not all 0"),
        (lambda: Perturbation(axis=(1.0, math.nan, 0.0)), "a direction needs 3 finite values"),
        (lambda: Perturbation(shift_m=(0.0, math.inf, 0.0)), "shift_m must be 3 finite metres"),
        (lambda: Perturbation(focal_scale=0.0), "focal_scale must be a factor from 0.001 to 1000"),
        (lambda: TiltSampler(limit_deg=-1.0), r"TiltSampler.limit_deg must be a finite number in \[0, 180\]"),
        (lambda: ArcSampler(limit_deg=180.5), r"ArcSampler.limit_deg must be a finite number in \[0, 180\]"),
        (lambda: ArcSampler(45.0, shift_m=math.nan), r"ArcSampler.shift_m must be a finite number in"),
        (lambda: TiltSampler(10.0, shift_m=math.inf), r"TiltSampler.shift_m must be a finite number in \[0, inf\]"),
        (lambda: ArcSampler(45.0, focal_scale=(1.2, 0.8)), r"ArcSampler.focal_scale: need 0 < low <= high"),
        (lambda: make_sampler("zoom"), "unknown perturbation sampler 'zoom'"),
        (lambda: Perturbation(theta_deg=math.nan), "finite"),
        (lambda: Perturbation(mu_m=math.inf), "finite"),
        (lambda: axis_rotation("w", 10.0), "axis must be one of"),
        (lambda: perturb_pose(torch.eye(4), torch.zeros(3), "Y", 10.0, 0.0), "axis must be one of"),
        (lambda: PerturbationRange((5.0, 1.0), (0.0, 0.1)), r"theta_deg: need finite low <= high"),
        (lambda: PerturbationRange((1.0, 5.0), (0.1, math.nan)), r"mu_m: need finite low <= high"),
        (lambda: PerturbationRange((-5.0, 5.0), (0.0, 0.1)), "magnitude range"),
    ],
)
def test_bad_arguments_raise_clear_value_errors(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_move_perturbs_one_camera_of_a_rig_about_its_pivot():
    from gensplat_transforms.data.scenes import default_cameras

    cams = default_cameras(32, 32)
    p = Perturbation("x", 12.0, 0.03)
    moved = p.move(cams, 1)
    expected = p.apply(cams.c2w[1:2], pivot_point(cams.c2w[0], cams.c2w[1]))
    torch.testing.assert_close(moved.c2w, expected)
    torch.testing.assert_close(moved.K, cams.K[1:2])
    assert len(moved) == 1
    for bad in (-1, len(cams)):
        with pytest.raises(IndexError, match="camera index"):
            p.move(cams, bad)


def test_move_checks_the_moved_pose_only_for_overflow(monkeypatch):
    """The move is a rigid motion of a checked pose, so the rotation checks are not repeated;
    a pose that overflows (cameras near float64's largest value) still raises."""
    from gensplat_transforms.core import cameras as cameras_module
    from gensplat_transforms.data.scenes import default_cameras

    cams = default_cameras(32, 32)
    monkeypatch.setattr(cameras_module, "_check_rigid", lambda c2w, tolerance: pytest.fail("checked again"))
    Perturbation("y", -20.0, 0.05).move(cams, 0)
    monkeypatch.undo()
    far = cams.c2w.clone()
    far[0, :3, 3], far[1, :3, 3] = 1.5e308, -1.5e308
    with pytest.raises(ValueError, match="Cameras.c2w: contains NaN or Inf"):
        Perturbation("y", -20.0, 0.05).move(cams.with_c2w(far), 0)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.float16])
@pytest.mark.parametrize("axis", ["x", "y"])
def test_axis_rotation_has_kornias_bits(axis, dtype):
    """The NumPy evaluation of kornia's formula gives its bits (signed zeros included), on
    both of its branches: Rodrigues' formula and the Taylor series below 1e-3 rad."""
    from kornia.geometry.conversions import axis_angle_to_rotation_matrix

    rng = np.random.default_rng(AXES.index(axis))
    angles = [*rng.uniform(-200, 200, 300), *rng.uniform(-0.12, 0.12, 200), 0.0, -0.0, 0.0572958, -0.0572958,
              1e-9, 30.0, -60.0, 90.0, 180.0]  # fmt: skip
    for theta in angles:
        axis_angle = torch.zeros(3, dtype=dtype)
        axis_angle[AXES.index(axis)] = math.radians(theta)
        want, got = axis_angle_to_rotation_matrix(axis_angle), axis_rotation(axis, theta, dtype)
        assert got.dtype == dtype
        assert torch.equal(got, want) and torch.equal(got.signbit(), want.signbit()), theta


def test_batched_moves_equal_one_move_at_a_time():
    """perturb_pose and pivot_point over (S, T, ...) batches give each element's own move,
    a parallel pair among them included (its pivot falls back to the centres' midpoint)."""
    g = torch.Generator().manual_seed(0)
    eyes = [(1.0, 0.5, 0.5), (1.0, -0.5, 0.5), (0.8, 0.0, 0.9), (0.5, 0.6, 0.4)]
    c2w = torch.stack([look_at(e, (0.0, 0.0, 0.1 * i)) for i, e in enumerate(eyes)]).reshape(2, 2, 4, 4)
    c2w[1, 1] = c2w[1, 0].clone()
    c2w[1, 1, :3, 3] += torch.tensor([0.0, 0.3, 0.0], dtype=DTYPE)  # parallel axes
    pivots = pivot_point(c2w[:, 0], c2w[:, 1])
    for s in range(2):
        torch.testing.assert_close(pivots[s], pivot_point(c2w[s, 0], c2w[s, 1]), rtol=0, atol=1e-15)
    torch.testing.assert_close(pivots[1], 0.5 * (c2w[1, 0, :3, 3] + c2w[1, 1, :3, 3]))
    index = torch.tensor([[0, 1], [1, 2]])
    theta = torch.empty(2, 2, dtype=DTYPE).uniform_(-30, 30, generator=g)
    mu = torch.empty(2, 2, dtype=DTYPE).uniform_(0, 0.06, generator=g)
    shift = torch.empty(2, 2, 3, dtype=DTYPE).uniform_(-0.03, 0.03, generator=g)
    moved = perturb_pose(c2w, pivots[:, None], torch.eye(3, dtype=DTYPE)[index], theta, mu)
    shifted = perturb_pose(c2w, pivots[:, None], torch.eye(3, dtype=DTYPE)[index], theta, mu, shift)
    for s in range(2):
        for v in range(2):
            one = perturb_pose(c2w[s, v], pivots[s], AXES[int(index[s, v])], float(theta[s, v]), float(mu[s, v]))
            torch.testing.assert_close(moved[s, v], one, rtol=0, atol=1e-15)  # batched products: last-bit round-off
            torch.testing.assert_close(shifted[s, v, :3, 3], one[:3, 3] + shift[s, v], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match=r"axis directions must be \(\.\.\., 3\), got \(2, 2\)"):
        perturb_pose(c2w, pivots[:, None], index, theta, mu)


# ---------------------------------------------------------------------------- wider samplers
def test_tilt_sampler_draws_random_axes_angles_and_shifts_within_its_ranges():
    """Axes uniform on the sphere (mean near 0, each component's |mean| of squares near 1/3),
    angles uniform in [-tilt, tilt], shifts in the box; seeded, salted apart from the paper's."""
    s = TiltSampler(limit_deg=12.0, shift_m=0.04, seed=3)
    moves = [s.sample(ep) for ep in range(2000)]
    axes = torch.tensor([m.axis for m in moves])
    assert axes.mean(0).abs().max() < 0.05 and (axes.square().mean(0) - 1 / 3).abs().max() < 0.03
    theta = torch.tensor([m.theta_deg for m in moves])
    assert theta.abs().max() <= 12.0 and abs(float(theta.mean())) < 0.5 and float(theta.abs().mean()) == pytest.approx(6.0, abs=0.3)
    shift = torch.tensor([m.shift_m for m in moves])
    assert shift.abs().max() <= 0.04 and float(shift.abs().mean()) == pytest.approx(0.02, abs=0.002)
    assert all(m.mu_m == 0.0 and m.focal_scale == 1.0 and m.about == "camera" for m in moves)
    assert s.sample(5) == TiltSampler(limit_deg=12.0, shift_m=0.04, seed=3).sample(5) != s.sample(6)
    assert s.sample(5) == s.sample(5, frame_index=9) != TiltSampler(12.0, 0.04, mode="frame", seed=3).sample(5, 9)


def test_arc_sampler_turns_about_the_vertical_and_keeps_the_pivot_in_view():
    """Turns about world z through the pivot within +-arc; with no step, the pivot stays where
    the camera saw it (the same camera-frame point), the camera's height is kept, and the move
    is rigid."""
    left, right = look_at((1.05, 0.4, 0.5), (0.45, 0.0, 0.12)), look_at((1.05, -0.4, 0.5), (0.45, 0.0, 0.12))
    cameras = Cameras(torch.tensor([[100.0, 0, 32], [0, 100.0, 32], [0, 0, 1]], dtype=DTYPE).expand(2, 3, 3),
                      torch.stack([left, right]), 64, 64)  # fmt: skip
    pivot = pivot_point(left, right)
    s = ArcSampler(limit_deg=45.0, shift_m=0.0, seed=1)
    for ep in range(50):
        p = s.sample(ep)
        assert p.axis == "z" and abs(p.theta_deg) <= 45.0 and p.mu_m == 0.0
        moved = p.move(cameras, 0).c2w[0]
        seen = lambda c2w: (torch.linalg.inv(c2w) @ torch.cat([pivot, torch.ones(1, dtype=DTYPE)]))[:3]
        torch.testing.assert_close(seen(moved), seen(left), rtol=0, atol=1e-12)
        assert float(moved[2, 3]) == pytest.approx(float(left[2, 3]), abs=1e-12)
        torch.testing.assert_close(moved[:3, :3] @ moved[:3, :3].T, torch.eye(3, dtype=DTYPE), rtol=0, atol=1e-12)
    thetas = torch.tensor([s.sample(ep).theta_deg for ep in range(2000)])
    assert float(thetas.min()) < -43 and float(thetas.max()) > 43 and abs(float(thetas.mean())) < 1.5


def test_a_focal_length_change_keeps_the_move_the_principal_point_and_the_image_size():
    """focal_scale is drawn log-uniformly after the move, so the paper's draws are unchanged;
    the moved camera's focal lengths scale, its principal point and size stay."""
    plain, zoom = PaperSampler("large", seed=2), PaperSampler("large", seed=2, focal_scale=(0.8, 1.25))
    for ep in range(20):
        a, b = plain.sample(ep), zoom.sample(ep)
        assert (a.axis, a.theta_deg, a.mu_m) == (b.axis, b.theta_deg, b.mu_m) and 0.8 <= b.focal_scale <= 1.25
    logs = torch.tensor([math.log(zoom.sample(ep).focal_scale) for ep in range(3000)])
    assert abs(float(logs.mean())) < 0.01 and float(logs.min()) < math.log(0.81) and float(logs.max()) > math.log(1.24)
    cameras = Cameras(torch.tensor([[100.0, 0, 30], [0, 90.0, 34], [0, 0, 1]], dtype=DTYPE)[None],
                      look_at((1.0, 0.3, 0.5), (0, 0, 0))[None], 64, 48)  # fmt: skip
    moved = Perturbation("y", 0.0, 0.0, focal_scale=1.25).move(cameras, 0, pivot_depth=1.0)
    assert moved.K[0].tolist() == [[125.0, 0.0, 30.0], [0.0, 112.5, 34.0], [0.0, 0.0, 1.0]]
    assert (moved.width, moved.height) == (64, 48) and torch.equal(moved.c2w, cameras.c2w)


def test_make_sampler_and_the_config_choose_the_sampler():
    from gensplat_transforms.settings import GenSplatConfig

    assert isinstance(make_sampler("paper"), PaperSampler)
    config = GenSplatConfig(sampler="arc", arc_deg=30.0, shift_m=0.01, focal_scale=[0.9, 1.1])
    sampler = config.perturbations()
    assert isinstance(sampler, ArcSampler) and sampler.limit_deg == 30.0 and sampler.focal_scale == (0.9, 1.1)
    assert GenSplatConfig.from_dict(config.to_dict()) == config
    with pytest.raises(ValueError, match="unknown perturbation sampler 'orbit'"):
        GenSplatConfig(sampler="orbit")
    with pytest.raises(ValueError, match=r"^focal_scale: need 0 < low <= high, got \(0.0, 1.0\)"):
        GenSplatConfig(focal_scale=(0.0, 1.0))
    with pytest.raises(ValueError, match=r"^arc_deg must be a finite number in \[0, 180\], got -5.0"):
        GenSplatConfig(sampler="paper", arc_deg=-5.0)  # a bad setting is refused whichever sampler is chosen
    with pytest.raises(ValueError, match=r"^shift_m must be a finite number in \[0, inf\], got inf"):
        GenSplatConfig(sampler="tilt", shift_m=math.inf)


def test_the_mix_sampler_draws_each_kind_about_equally():
    s = make_sampler("mix", level="train", tilt_deg=10.0, arc_deg=45.0, shift_m=0.02, seed=4)
    kinds = [("tilt" if not isinstance(m.axis, str) else "arc" if m.axis == "z" else "paper")
             for m in (s.sample(ep) for ep in range(900))]  # fmt: skip
    assert all(250 < kinds.count(k) < 350 for k in ("paper", "tilt", "arc"))
    assert s.sample(7) == make_sampler("mix", seed=4, shift_m=0.02).sample(7) != s.sample(8)


def test_a_list_of_kinds_draws_one_of_them_per_move():
    from gensplat_transforms.settings import GenSplatConfig

    kind = lambda m: "tilt" if not isinstance(m.axis, str) else "arc" if m.axis == "z" else "paper"
    s = make_sampler("tilt,arc", seed=4, shift_m=0.02, focal_scale=(0.9, 1.1))
    kinds = [kind(m) for m in (s.sample(ep) for ep in range(600))]
    assert set(kinds) == {"tilt", "arc"} and 250 < kinds.count("tilt") < 350
    assert all(0.9 <= s.sample(ep).focal_scale <= 1.1 for ep in range(50))
    assert s.sample(7) == make_sampler(" tilt , arc", seed=4, shift_m=0.02, focal_scale=(0.9, 1.1)).sample(7)
    assert [make_sampler("paper,tilt,arc", seed=4).sample(ep) for ep in range(20)] == [
        make_sampler("mix", seed=4).sample(ep) for ep in range(20)]  # "mix" names all three
    for bad in ("tilt,tilt", "", "tilt,zoom", ",", "arc,", "Tilt", None):
        with pytest.raises(ValueError, match=r"^unknown perturbation sampler .*separated by commas"):
            make_sampler(bad)
    assert GenSplatConfig.from_dict(GenSplatConfig(sampler="tilt,arc").to_dict()).perturbations().sample(3) == (
        make_sampler("tilt,arc").sample(3))


def test_a_turn_about_the_camera_keeps_its_centre_and_moves_the_image():
    """``about="camera"``: the orientation turns, the centre stays (then the shift applies);
    the pivot, which a turn about the pivot keeps at the same image point, leaves the image
    centre by about f tan(theta). The row says where the turn is about, for move_rig."""
    left, right = look_at((1.05, 0.4, 0.5), (0.45, 0.0, 0.12)), look_at((1.05, -0.4, 0.5), (0.45, 0.0, 0.12))
    pivot = pivot_point(left, right)
    cams = Cameras.from_intrinsics(100.0, 100.0, 48.0, 48.0, torch.stack([left, right]), 96, 96)
    shift = (0.01, -0.02, 0.005)
    bumped = Perturbation("x", 8.0, shift_m=shift, about="camera")
    moved = bumped.move(cams, 0)
    torch.testing.assert_close(moved.centers[0], left[:3, 3] + torch.tensor(shift, dtype=DTYPE))
    torch.testing.assert_close(moved.c2w[0, :3, :3], axis_rotation("x", 8.0) @ left[:3, :3])
    sideways = tuple(left[:3, 0].tolist())  # the camera's own x axis: a pure tilt of the view
    plain = Perturbation(sideways, 8.0, about="camera").move(cams, 0)
    u = plain.project(pivot[None])[0][0, 0]  # the pivot was at the image centre
    assert (u - torch.tensor([48.0, 48.0], dtype=DTYPE)).norm() == pytest.approx(100 * math.tan(math.radians(8.0)))
    about_pivot = Perturbation(sideways, 8.0).move(cams, 0).project(pivot[None])[0][0, 0]
    torch.testing.assert_close(about_pivot, torch.tensor([48.0, 48.0], dtype=DTYPE))
    assert bumped.as_row()[-1] == 0.0 and Perturbation("x", 8.0).as_row()[-1] == 1.0
    assert bumped.as_dict()["about"] == "camera" and "about" not in Perturbation("x", 8.0).as_dict()
    rows = torch.tensor([bumped.as_row(), Perturbation("y", -5.0, 0.02).as_row()], dtype=DTYPE)
    both = move_rig(cams.c2w, rows, [0, 1])
    torch.testing.assert_close(both[0], moved.c2w[0], rtol=0, atol=1e-12)
    torch.testing.assert_close(both[1], Perturbation("y", -5.0, 0.02).move(cams, 1).c2w[0], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="Perturbation.about must be one of"):
        Perturbation("x", 1.0, about="world")


def test_moves_read_a_row_by_name_for_any_batch_shape():
    p = Perturbation((0.0, 3.0, 4.0), 12.0, -0.02, (0.01, 0.0, -0.03), 1.25, about="camera")
    rows = torch.tensor([p.as_row()] * 6, dtype=torch.float32).reshape(2, 3, ROW)
    m = Moves.of_rows(rows)
    assert m.axis.shape == m.shift_m.shape == (2, 3, 3) and m.theta_deg.shape == (2, 3)
    assert m.theta_deg.dtype == torch.float64
    torch.testing.assert_close(m.axis[1, 2], torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64))
    torch.testing.assert_close(m.shift_m[0, 0], torch.tensor([0.01, 0.0, -0.03], dtype=torch.float64))
    assert (m.theta_deg == 12.0).all() and (m.focal_scale == 1.25).all() and (m.pivot == 0).all()
    torch.testing.assert_close(m.mu_m, torch.full((2, 3), -0.02, dtype=torch.float64), rtol=0, atol=1e-8)
    for bad in (torch.zeros(2, ROW - 1), torch.zeros(()), [p.as_row()]):
        with pytest.raises(ValueError, match=rf"Moves: need \(\.\.\., {ROW}\) rows"):
            Moves.of_rows(bad)
