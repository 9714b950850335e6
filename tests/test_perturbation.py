"""Tests for gensplat_transforms.perturbation (the paper's pivot-and-push camera protocol)."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
import torch

from gensplat_transforms.cameras import Cameras, look_at
from gensplat_transforms.perturbation import (
    AXES,
    EVAL_LEVELS,
    LEVELS,
    Perturbation,
    PerturbationRange,
    PerturbationSampler,
    axis_rotation,
    closest_points_between_axes,
    get_range,
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
    out = [PerturbationSampler("large", seed=seed).sample(ep) for seed in range(3) for ep in range(100)]
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
    samples = [PerturbationSampler(level, seed=7).sample(ep) for ep in range(300)]
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
    samples = [PerturbationSampler("train", seed=0).sample(ep) for ep in range(400)]
    thetas = torch.tensor([s.theta_deg for s in samples])
    assert thetas.min() >= -30 and thetas.max() <= 30
    assert (thetas.abs() < 3).any()  # small angles occur: it is not a magnitude range mirrored


def test_episode_mode_shares_one_perturbation_per_episode():
    s = PerturbationSampler("large", mode="episode", seed=0)
    for ep in range(5):
        first = s.sample(ep, 0)
        assert all(s.sample(ep, frame) == first for frame in range(1, 50))
    assert len({s.sample(ep) for ep in range(20)}) == 20  # episodes differ


def test_frame_mode_differs_per_frame_but_is_repeatable():
    s = PerturbationSampler("large", mode="frame", seed=0)
    frames = [s.sample(3, frame) for frame in range(50)]
    assert len(set(frames)) == 50
    assert [s.sample(3, frame) for frame in range(50)] == frames


def test_views_give_different_perturbations_of_the_same_episode():
    s = PerturbationSampler("train", seed=0)
    views = [s.sample(0, view=v) for v in range(3)]
    assert len(set(views)) == 3
    assert s.sample(0, view=1) == views[1]


def test_seeding_is_deterministic_and_seeds_differ():
    a, b, c = (PerturbationSampler("medium", seed=s) for s in (11, 11, 12))
    seq = [a.sample(ep, view=v) for ep in range(10) for v in range(2)]
    assert seq == [b.sample(ep, view=v) for ep in range(10) for v in range(2)]
    assert seq != [c.sample(ep, view=v) for ep in range(10) for v in range(2)]
    # the sampler survives pickling (DataLoader workers are spawned) with the same stream
    d = pickle.loads(pickle.dumps(a))
    assert [d.sample(ep, view=v) for ep in range(10) for v in range(2)] == seq


def test_single_axis_sampler():
    s = PerturbationSampler("small", axes=("x",), seed=0)
    assert {s.sample(ep).axis for ep in range(50)} == {"x"}


def test_none_and_extreme_levels_are_fixed():
    assert PerturbationSampler("none").sample(4).is_identity
    e = PerturbationSampler("extreme").sample(4)
    assert abs(e.theta_deg) == 60.0 and e.mu_m == 0.12


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: PerturbationSampler("huge"), "unknown perturbation level 'huge'; choose one of"),
        (lambda: get_range("Large "), "unknown perturbation level"),
        (lambda: PerturbationSampler("large", mode="step"), "mode must be 'episode' or 'frame', got 'step'"),
        (lambda: PerturbationSampler("large", axes=("z",)), "axes must be a non-empty subset"),
        (lambda: PerturbationSampler("large", axes=()), "axes must be a non-empty subset"),
        (lambda: PerturbationSampler("large", seed=-1), "seed must be >= 0"),
        (lambda: PerturbationSampler("large").sample(-1), "indices must be >= 0"),
        (lambda: PerturbationSampler("large", mode="frame").sample(0, -2), "indices must be >= 0"),
        (lambda: Perturbation(axis="z"), "axis must be one of"),
        (lambda: Perturbation(theta_deg=math.nan), "finite"),
        (lambda: Perturbation(mu_m=math.inf), "finite"),
        (lambda: axis_rotation("z", 10.0), "axis must be one of"),
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
    from gensplat_transforms.scenes import default_cameras

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
    from gensplat_transforms import cameras as cameras_module
    from gensplat_transforms.scenes import default_cameras

    cams = default_cameras(32, 32)
    monkeypatch.setattr(cameras_module, "_check_rigid", lambda c2w: pytest.fail("checked again"))
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
    axis = torch.tensor([[0, 1], [1, 0]])
    theta = torch.empty(2, 2, dtype=DTYPE).uniform_(-30, 30, generator=g)
    mu = torch.empty(2, 2, dtype=DTYPE).uniform_(0, 0.06, generator=g)
    moved = perturb_pose(c2w, pivots[:, None], axis, theta, mu)
    for s in range(2):
        for v in range(2):
            one = perturb_pose(c2w[s, v], pivots[s], AXES[int(axis[s, v])], float(theta[s, v]), float(mu[s, v]))
            torch.testing.assert_close(moved[s, v], one, rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match=r"axis indices must be 0 \(x\) or 1 \(y\), got \[0, 2\]"):
        perturb_pose(c2w, pivots[:, None], torch.tensor([[0, 2], [0, 0]]), theta, mu)
