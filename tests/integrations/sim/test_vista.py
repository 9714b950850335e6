"""VISTA's camera samplers (gensplat_sim.vista) and the "vista" evaluation protocol of
PerturbedCameraEnv: the samplers' statistics, rigid and reproducible poses, the arc camera
looking at the centre, and the default protocol left as it was."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from gensplat_sim.vista import ArcMove, SmallPerturb, VistaSampler

from gensplat_transforms.core.cameras import look_at
from gensplat_transforms.views.perturbation import PaperSampler

EYE, CENTRE = (
    (1.05, 0.40, 0.50),
    torch.tensor([0.45, 0.0, 0.12], dtype=torch.float64),
)  # the sim's left camera
NOMINAL = look_at(EYE, CENTRE)
N = 4000


def draws(name: str, n: int = N, seed: int = 0) -> list:
    sampler = VistaSampler(name, seed=seed)
    return [sampler.sample(i) for i in range(n)]


def assert_rigid(c2w: torch.Tensor) -> None:
    assert c2w.shape == (4, 4) and c2w.dtype == torch.float64 and torch.isfinite(c2w).all()
    R = c2w[:3, :3]
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=torch.float64), atol=1e-9, rtol=0)
    assert abs(float(torch.linalg.det(R)) - 1) < 1e-9
    torch.testing.assert_close(c2w[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64))


def rotation_angle(R: torch.Tensor) -> float:
    return math.acos(max(-1.0, min(1.0, (float(torch.trace(R)) - 1) / 2)))


def test_small_perturb_statistics():
    moves = draws("small_perturb")
    offsets = np.array([m.offset_m for m in moves])
    angles = np.array([m.angle_rad for m in moves])
    axes = np.array([m.rotation_axis for m in moves])
    # position noise: 3 cm per axis, zero mean, independent axes (std error ~1.1 % at N = 4000)
    np.testing.assert_allclose(offsets.std(axis=0), 0.03, rtol=0.05)
    assert np.abs(offsets.mean(axis=0)).max() < 4 * 0.03 / math.sqrt(N)
    assert np.abs(np.corrcoef(offsets.T) - np.eye(3)).max() < 0.06
    # rotation angle: Gaussian with std 0.075 rad about unit axes spread uniformly over the sphere
    assert abs(angles.std() - 0.075) < 0.05 * 0.075 and abs(angles.mean()) < 0.005
    np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-12)
    assert np.abs(axes.mean(axis=0)).max() < 0.05 and np.abs(axes.T @ axes / N - np.eye(3) / 3).max() < 0.03
    # the applied pose: moved by the offset, turned by |angle| about the axis
    for m in moves[:50]:
        c2w = m.apply(NOMINAL, CENTRE)
        assert_rigid(c2w)
        torch.testing.assert_close(c2w[:3, 3] - NOMINAL[:3, 3], torch.tensor(m.offset_m, dtype=torch.float64))
        delta = c2w[:3, :3] @ NOMINAL[:3, :3].T
        assert rotation_angle(delta) == pytest.approx(abs(m.angle_rad), abs=1e-9)
        torch.testing.assert_close(delta @ torch.tensor(m.rotation_axis, dtype=torch.float64),
                                   torch.tensor(m.rotation_axis, dtype=torch.float64), atol=1e-9, rtol=0)  # fmt: skip


def test_arc_statistics_and_look_at():
    moves = draws("arc_90deg")
    azimuths = np.array([m.azimuth_deg for m in moves])
    noise = np.array([m.radius_noise_m for m in moves])
    # azimuth uniform on +-45 deg: within the arc, reaching both ends, std 90 / sqrt(12)
    assert np.abs(azimuths).max() <= 45 and azimuths.min() < -44 and azimuths.max() > 44
    assert abs(azimuths.std() - 2 * 45 / math.sqrt(12)) < 1.0
    assert abs(noise.std() - 0.05) < 0.05 * 0.05 and abs(noise.mean()) < 0.003
    offset = NOMINAL[:3, 3] - CENTRE
    distance, height = float(offset.norm()), float(offset[2])
    base = math.degrees(math.atan2(offset[1], offset[0]))
    for m in moves[:200]:
        c2w = m.apply(NOMINAL, CENTRE)
        assert_rigid(c2w)
        eye_offset = c2w[:3, 3] - CENTRE
        radius = float(eye_offset.norm())
        assert radius == pytest.approx(distance + m.radius_noise_m, abs=1e-9)
        # on the arc: turned by the azimuth about the vertical axis, the elevation kept
        assert math.degrees(math.atan2(eye_offset[1], eye_offset[0])) - base == pytest.approx(
            m.azimuth_deg, abs=1e-6
        )
        assert float(eye_offset[2]) / radius == pytest.approx(height / distance, abs=1e-9)
        # looking at the centre (+z towards it), image up towards world +z (x horizontal, y down)
        torch.testing.assert_close(c2w[:3, 2], -eye_offset / radius, atol=1e-9, rtol=0)
        assert abs(float(c2w[2, 0])) < 1e-9 and float(c2w[2, 1]) < 0
    # no turn, no noise: the nominal camera (it looks at the centre with world up)
    torch.testing.assert_close(ArcMove(0.0, 0.0).apply(NOMINAL, CENTRE), NOMINAL, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="noise"):
        ArcMove(10.0, -distance - 0.01).apply(NOMINAL, CENTRE)


def test_samplers_are_seeded_per_episode():
    for name in ("small_perturb", "arc_90deg"):
        a, b = VistaSampler(name, seed=3), VistaSampler(name, seed=3)
        assert [a.sample(i) for i in range(5)] == [b.sample(i) for i in (0, 1, 2, 3, 4)]
        assert b.sample(7) == a.sample(7)  # the draw depends on the episode, not on the order of calls
        assert a.sample(0) != a.sample(1) and a.sample(0) != VistaSampler(name, seed=4).sample(0)
        assert isinstance(a.sample(0), SmallPerturb if name == "small_perturb" else ArcMove)
        assert set(a.sample(0).as_dict()) == set(a.sample(0).__dataclass_fields__)
    with pytest.raises(ValueError, match="unknown VISTA sampler"):
        VistaSampler("large")
    with pytest.raises(ValueError, match="seed"):
        VistaSampler("arc_90deg", seed=-1)


def test_perturbed_camera_env_protocols():
    pytest.importorskip("mujoco", reason="the simulated world needs the 'sim' extra (mujoco, gym-hil)")
    import gensplat_sim  # noqa: F401  (selects the headless GL backend before MuJoCo loads)
    from gensplat_sim.evaluate import EvalConfig, PerturbedCameraEnv
    from gensplat_sim.world import WorldConfig

    world = WorldConfig(height=32, width=32)
    paper = PerturbedCameraEnv(EvalConfig("reach_solo", "medium", seed=5, world=world))
    assert paper.config.protocol == "paper"  # the default, drawn as before the VISTA protocol
    arc = PerturbedCameraEnv(EvalConfig("reach_solo", "arc_90deg", seed=5, world=world, protocol="vista"))
    for i in range(2):
        _, info = paper.reset(options={"episode_index": i})
        assert info["perturbation"] == PaperSampler("medium", seed=5).sample(i).as_dict()
        obs, info = arc.reset(options={"episode_index": i})
        move = VistaSampler("arc_90deg", seed=5).sample(i)
        assert info["perturbation"] == move.as_dict()
        moved = arc.world.cameras(("left", "right")).c2w
        target = torch.tensor(world.scene.external["left"].target, dtype=torch.float64)
        torch.testing.assert_close(moved[0], move.apply(arc.nominal_c2w["left"], target), atol=1e-6, rtol=0)
        torch.testing.assert_close(moved[1], arc.nominal_c2w["right"], atol=1e-6, rtol=0)
        assert obs["observation.images.left"].shape == (3, 32, 32)
    # the same seeds give the same layouts under both protocols: only the camera differs
    paper.reset(options={"episode_index": 1})
    assert paper.world.episode == arc.world.episode
    zoom = PerturbedCameraEnv(EvalConfig("reach_solo", "zoom", seed=5, world=world, protocol="fov"))
    nominal = zoom.world.cameras(("left", "right"))
    for i in range(3):
        _, info = zoom.reset(options={"episode_index": i})
        scale = PaperSampler("none", seed=5, focal_scale=(0.8, 1.25)).sample(i).focal_scale
        assert info["perturbation"]["focal_scale"] == scale and 0.8 <= scale <= 1.25
        seen = zoom.world.cameras(("left", "right"))
        torch.testing.assert_close(seen.K[0, :2, :2], nominal.K[0, :2, :2] * scale, atol=1e-4, rtol=0)
        torch.testing.assert_close(seen.K[1], nominal.K[1], atol=1e-9, rtol=0)  # only "left" is perturbed
        torch.testing.assert_close(seen.c2w, nominal.c2w, atol=1e-6, rtol=0)  # nothing moves
    for env in (paper, arc, zoom):
        env.close()
    with pytest.raises(ValueError, match="the fov protocol has one level, 'zoom'"):
        PerturbedCameraEnv(EvalConfig("reach_solo", "large", world=world, protocol="fov"))
    with pytest.raises(ValueError, match="protocol"):
        PerturbedCameraEnv(EvalConfig("reach_solo", "small", world=world, protocol="ours"))
    with pytest.raises(ValueError, match="VISTA sampler"):
        PerturbedCameraEnv(EvalConfig("reach_solo", "small", world=world, protocol="vista"))
