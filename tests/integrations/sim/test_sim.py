"""Simulated Franka tabletop: determinism, calibration, experts, LeRobot recording, ground truth
and the perturbed-camera evaluation environment. Images are 96x96 to keep the suite fast."""

from __future__ import annotations

import math
from dataclasses import replace

import gensplat_sim  # noqa: F401  (selects the headless GL backend before MuJoCo loads)
import numpy as np
import pytest
import torch

mujoco = pytest.importorskip("mujoco", reason="the simulated world needs the 'sim' extra (mujoco, gym-hil)")

from gensplat_sim.evaluate import EvalConfig, PerturbedCameraEnv, evaluate, paired_difference
from gensplat_sim.experts import ExpertPolicy, run_expert
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.scene import ObjectSpec
from gensplat_sim.tasks import REACH_CLEARANCE, TASKS, Task, episode_seed
from gensplat_sim.truth import GroundTruth, load_sim_episode
from gensplat_sim.world import CAMERA_NAMES, SimWorld, WorldConfig

from gensplat_transforms.calibration.files import load_calibration
from gensplat_transforms.data.format import load_depth
from gensplat_transforms.views.perturbation import PaperSampler, Perturbation, pivot_point

SIZE = 96


def small_config() -> WorldConfig:
    return WorldConfig(height=SIZE, width=SIZE)


@pytest.fixture(scope="module")
def world() -> SimWorld:
    w = SimWorld("pick_place", small_config())
    yield w
    w.close()


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """One lossless (PNG) pick-and-place episode recorded at 96x96."""
    root = tmp_path_factory.mktemp("sim") / "dataset"
    result = record(
        RecordConfig(root, task="pick_place", episodes=1, seed=3, use_videos=False, world=small_config()),
        progress=False,
    )
    return result


def test_same_seed_same_episode(world):
    ep_a, states_a, actions_a, _ = run_expert(world, seed=11)
    frame_a = world.render(("left",))["left"]
    ep_b, states_b, actions_b, _ = run_expert(world, seed=11)
    frame_b = world.render(("left",))["left"]
    assert ep_a == ep_b
    np.testing.assert_array_equal(actions_a, actions_b)
    np.testing.assert_array_equal(np.stack([s.qpos for s in states_a]), np.stack([s.qpos for s in states_b]))
    np.testing.assert_array_equal(frame_a[0], frame_b[0])
    np.testing.assert_array_equal(frame_a[1], frame_b[1])
    ep_c = world.task.sample(12)
    assert ep_c.placements != ep_a.placements


def test_episode_seeds_separate_streams():
    seeds = {episode_seed(0, i, s) for i in range(50) for s in ("record", "eval")}
    assert len(seeds) == 100


@pytest.mark.parametrize("task", sorted(TASKS))
def test_experts_succeed(task):
    w = SimWorld(task, small_config())
    results = [run_expert(w, episode_seed(0, i))[3] for i in range(3)]
    w.close()
    assert all(results), f"{task}: expert failed on seeds {[i for i, r in enumerate(results) if not r]}"


def test_reach_success_needs_the_open_gripper_at_the_goal():
    task = TASKS["reach"]
    cube = np.array([0.5, 0.1, 0.02])
    positions = {"cube": cube, "plate": np.array([0.4, -0.1, 0.006]), "can": np.array([0.6, 0.0, 0.045])}
    goal = task.reach_goal(cube)
    np.testing.assert_allclose(goal, cube + [0, 0, 0.02 + REACH_CLEARANCE])
    assert task.success(positions, gripper_closed=False, pinch=goal + [0.02, 0, 0])
    assert not task.success(positions, gripper_closed=False, pinch=goal + [0.0, 0.03, 0])
    assert not task.success(positions, gripper_closed=False, pinch=goal + [0.0, 0, 0.03])
    assert not task.success(positions, gripper_closed=True, pinch=goal)
    episode = task.sample(3)
    assert episode.instruction == f"reach the {episode.placements['cube'].color} cube"


def test_reach_solo_draws_contrasting_colours_only():
    task = TASKS["reach_solo"]
    colours = {task.sample(seed).placements["cube"].color for seed in range(200)}
    assert colours == set(task.colors) and not colours & {"yellow", "orange", "pink"}


def test_reach_expert_starts_away_from_the_goal():
    """A reach is not won at reset: the expert needs a dozen or more steps to get there."""
    w = SimWorld("reach", small_config())
    w.reset(episode_seed(0, 0))
    assert not w.success()
    _, _, actions, success = run_expert(w, episode_seed(0, 0))
    w.close()
    assert success and 10 <= len(actions) <= 40


def _marker_world(height: int = 224, width: int = 224) -> tuple[SimWorld, int]:
    """A pick-and-place world with a 8 mm ball (segmentation marker) floating at a known point."""
    base = TASKS["pick_place"]
    task = Task(
        "pick_place",
        base.objects + (ObjectSpec("ball", "sphere", (0.008,), 0.01),),
        "cube",
        "plate",
        "cube",
        "plate",
        0.06,
    )
    w = SimWorld(task, WorldConfig(height=height, width=width))
    w.reset(0)
    return w, w.model.geom("ball").id


def _place_ball(w: SimWorld, point: np.ndarray) -> None:
    adr = w.model.joint("ball").qposadr[0]
    w.data.qpos[adr : adr + 3] = point
    mujoco.mj_forward(w.model, w.data)


def _centroid(seg: np.ndarray, geom: int) -> np.ndarray:
    rows, cols = np.nonzero(seg == geom)
    assert len(rows) > 5, "marker not visible"
    return np.array([cols.mean() + 0.5, rows.mean() + 0.5])  # pixel centres at +0.5


@pytest.mark.parametrize("height, width", [(224, 224), (168, 224)])
def test_calibration_round_trip(height, width):
    """Projection through the calibration lands on the rendered marker, square or not (MuJoCo's
    fovy is vertical: f = (H / 2) / tan(fovy / 2), principal point at (W / 2, H / 2))."""
    w, ball = _marker_world(height, width)
    point = np.array([0.52, 0.07, 0.15])
    _place_ball(w, point)
    cams = w.cameras(CAMERA_NAMES)
    assert (cams.width, cams.height) == (width, height)
    f = height / 2 / np.tan(np.radians(w.model.cam_fovy[[w.model.camera(n).id for n in CAMERA_NAMES]]) / 2)
    np.testing.assert_allclose(cams.K[:, 0, 0], f)
    np.testing.assert_allclose(cams.K[:, 1, 1], f)
    np.testing.assert_allclose(cams.K[:, :2, 2], np.tile([width / 2, height / 2], (3, 1)))
    uv, z = cams.project(torch.tensor(point)[None])
    for i, name in enumerate(CAMERA_NAMES):
        c = _centroid(w.segmentation(name), ball)
        assert np.abs(c - uv[i, 0].numpy()).max() < 0.5, f"{name}: marker at {c}, projection {uv[i, 0]}"
        depth = w.render((name,))[name][1]
        front = float(z[i, 0]) - 0.008  # nearest point of the ball
        assert abs(depth[int(c[1]), int(c[0])] - front) < 2e-3

    # an arbitrary (Large-level) camera pose through render_at's probe camera
    pivot = pivot_point(cams.c2w[0], cams.c2w[1])
    moved = cams[0].with_c2w(Perturbation("x", 25.0, 0.05).apply(cams.c2w[:1], pivot))
    rgb, depth = w.render_at(moved)
    assert rgb.shape == (1, 3, height, width) and depth.shape == (1, 1, height, width)
    seg = w.renderer().segmentation(w.data, w.model.camera("probe").id)
    uv, _ = moved.project(torch.tensor(point)[None])
    assert np.abs(_centroid(seg, ball) - uv[0, 0].numpy()).max() < 0.5

    # render_at at a dataset camera reproduces that camera exactly
    rgb, depth = w.render_at(cams[:1])
    ref_rgb, ref_depth = w.render(("left",))["left"]
    np.testing.assert_array_equal((rgb[0].permute(1, 2, 0) * 255).round().byte().numpy(), ref_rgb)
    np.testing.assert_array_equal(depth[0, 0].numpy(), ref_depth)
    w.close()


def test_depth_is_metric_camera_z(world):
    """Rendered depth equals MuJoCo ray casting through the pixel centres (no MSAA offset)."""
    world.reset(0)
    cam = world.cameras(("left",))
    _, depth = world.render(("left",))["left"]
    rng = np.random.default_rng(0)
    pix = rng.integers(0, SIZE, size=(40, 2))
    uv = torch.tensor(pix + 0.5, dtype=torch.float64)[None]
    far = cam.unproject(uv, torch.ones(1, len(pix), dtype=torch.float64))[0].numpy()
    origin = cam.c2w[0, :3, 3].numpy()
    seg = world.segmentation("left")
    checked = 0
    for (u, v), p in zip(pix, far):
        d = p - origin
        geom = np.array([-1], dtype=np.int32)
        t = mujoco.mj_ray(world.model, world.data, origin, d / np.linalg.norm(d), None, 1, -1, geom)
        if geom[0] == seg[v, u] >= 0:  # ray casting also sees collision-only geoms; compare where both agree
            checked += 1
            assert depth[v, u] == pytest.approx(t / np.linalg.norm(d), rel=1e-4, abs=1e-4)
    assert checked > 20


def test_dataset_loads_with_lerobot(recorded):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("gensplat/sim_pick_place", root=recorded.root)
    assert ds.meta.total_episodes == 1 and len(ds) == recorded.frames
    item = ds[5]
    for name in CAMERA_NAMES:
        assert item[f"observation.images.{name}"].shape == (3, SIZE, SIZE)
    assert item["observation.state"].shape == (12,) and item["action"].shape == (5,)
    assert item["task"].startswith("put the ") and item["task"].endswith(" plate")

    calib = load_calibration(ds.meta.features)
    assert list(calib) == list(CAMERA_NAMES)
    assert calib["wrist"].mount == "wrist" and calib["wrist"].c2w is None
    w = SimWorld("pick_place", small_config())
    truth = w.cameras(("left", "right"))
    for i, name in enumerate(("left", "right")):
        assert calib[name].mount == "external"
        torch.testing.assert_close(calib[name].K, truth.K[i])
        torch.testing.assert_close(calib[name].c2w, truth.c2w[i])
    w.close()

    depth = load_depth(recorded.root, "left", 0)
    assert depth.shape == (recorded.frames, 1, SIZE, SIZE) and depth.dtype == torch.float32
    assert (depth > 0.2).float().mean() > 0.99 and depth.max() < 6.0


def test_ground_truth_matches_recording(recorded):
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    ds = LeRobotDataset("gensplat/sim_pick_place", root=recorded.root)
    truth = GroundTruth(recorded.root)
    episode, states = load_sim_episode(recorded.root, 0)
    assert len(states) == recorded.frames and truth.num_frames(0) == recorded.frames
    depth = load_depth(recorded.root, "right", 0)
    for t in (0, recorded.frames // 2, recorded.frames - 1):
        item = ds[t]
        cams = truth.cameras(0, t, CAMERA_NAMES)
        rgb, d = truth.render(0, t, cams)
        for i, name in enumerate(CAMERA_NAMES):
            assert (rgb[i] - item[f"observation.images.{name}"]).abs().max() <= 1 / 255 + 1e-6, name
        torch.testing.assert_close(d[1], depth[t], rtol=1e-3, atol=1e-3)
        np.testing.assert_allclose(truth.world.robot_state(), item["observation.state"].numpy(), atol=1e-6)
    assert truth.world.episode == episode
    truth.close()


def test_perturbed_camera_env():
    config = EvalConfig(task="pick_place", level="large", seed=2, world=small_config())
    env = PerturbedCameraEnv(config)
    expert = ExpertPolicy(env.world)
    result = evaluate(expert, env, episodes=1, reset=expert.reset)
    assert result.successes == [True] and 0 < result.steps[0] < env.max_steps
    assert result.lifted == [True] and result.reach_m[0] < 0.02 and result.lift_rate == 1.0

    def hold(obs):  # stay where the arm starts, gripper open
        return np.concatenate([obs["observation.state"][:4].numpy(), [0.0]])

    still = evaluate(hold, PerturbedCameraEnv(replace(config, max_steps=5)), episodes=1)
    assert still.successes == [False] and still.lifted == [False] and still.reach_m[0] > 0.05

    reach = PerturbedCameraEnv(replace(config, task="reach"))
    expert = ExpertPolicy(reach.world)
    reached = evaluate(expert, reach, episodes=1, reset=expert.reset)
    reach.close()
    # a reach ends as soon as the pinch point is within the task's tolerance of the goal
    assert reached.successes == [True] and reached.reach_m[0] < TASKS["reach"].place_tolerance
    assert reached.lifted == [False]

    def jitter(obs):  # a stochastic policy: torch's global generator, as a diffusion policy
        return np.concatenate([obs["observation.state"][:4].numpy() + 0.05 * torch.randn(4).numpy(), [0.0]])

    short = PerturbedCameraEnv(replace(config, max_steps=4))
    first, again = (evaluate(jitter, short, episodes=2).reach_m for _ in range(2))
    short.close()
    assert first == again  # unseeded, the noise (and the arm) would differ between the two runs

    obs, info = env.reset(options={"episode_index": 0})
    p = PaperSampler("large", seed=2).sample(0)
    assert info["perturbation"] == p.as_dict() and abs(p.theta_deg) >= 18
    moved = env.world.cameras(("left", "right"))
    torch.testing.assert_close(moved.c2w[0], p.apply(env.nominal_c2w["left"], env.pivot), atol=1e-6, rtol=0)
    torch.testing.assert_close(moved.c2w[1], env.nominal_c2w["right"], atol=1e-6, rtol=0)
    assert obs["observation.images.left"].shape == (3, SIZE, SIZE) and obs["task"] == info["instruction"]
    rgb, _ = env.world.render_at(moved[:1])
    torch.testing.assert_close(obs["observation.images.left"], rgb[0], atol=1 / 255, rtol=0)
    env.close()


@pytest.mark.slow
def test_video_dataset_close_to_truth(tmp_path):
    """Default storage (AV1 video, 224x224): decoded frames stay close to the true render."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    result = record(RecordConfig(tmp_path / "video", task="stack", episodes=1, seed=0), progress=False)
    ds = LeRobotDataset("gensplat/sim_stack", root=result.root)
    truth = GroundTruth(result.root)
    t = result.frames // 2
    rgb, _ = truth.render(0, t, truth.cameras(0, t, ("left",)))
    mse = float(((rgb[0] - ds[t]["observation.images.left"]) ** 2).mean())
    assert 10 * math.log10(1 / mse) > 30
    truth.close()


def test_paired_difference():
    same = paired_difference([True, False] * 10, [True, False] * 10)
    assert same["points"] == 0 and same["ci95"] == [0, 0] and same["mcnemar_p"] == 1.0
    # b solves 8 episodes a failed, a solves none that b failed: 40 points, p = 2 / 2**8
    a, b = [False] * 8 + [True] * 12, [True] * 20
    r = paired_difference(a, b)
    assert r["points"] == 40 and (r["a_only"], r["b_only"]) == (0, 8)
    assert r["mcnemar_p"] == float(f"{2 / 2**8:.3g}") and 15 < r["ci95"][0] < 40 < r["ci95"][1] < 65
    # a 21 / 1 split of 100 episodes: p = 2 * 23 / 2**22, small but not zero
    r = paired_difference([False] * 21 + [True] + [False] * 78, [True] * 21 + [False] * 79)
    assert r["mcnemar_p"] == float(f"{46 / 2**22:.3g}") > 0
    assert paired_difference(b, a)["points"] == -40
    with pytest.raises(ValueError, match="equal"):
        paired_difference([True], [True, False])


def test_kept_scheduling_gives_the_thread_its_policy_back(monkeypatch):
    """What the AV1 encoder does to a thread of root's (SCHED_FIFO, priority 99) is undone."""
    import os

    from gensplat_sim.record import kept_scheduling

    state = {"policy": 0, "param": os.sched_param(0)}
    monkeypatch.setattr(os, "sched_getscheduler", lambda pid: state["policy"])
    monkeypatch.setattr(os, "sched_getparam", lambda pid: state["param"])
    monkeypatch.setattr(os, "sched_setscheduler", lambda pid, policy, param: state.update(policy=policy, param=param))
    with kept_scheduling():
        state.update(policy=1, param=os.sched_param(99))  # what the encoder does
    assert state == {"policy": 0, "param": os.sched_param(0)}
    with pytest.raises(RuntimeError), kept_scheduling():  # also when the block fails
        state.update(policy=1, param=os.sched_param(99))
        raise RuntimeError
    assert state["policy"] == 0


def test_reach_marked_reaches_the_red_cube_beside_a_decoy_of_another_colour():
    task = TASKS["reach_marked"]
    episodes = [task.sample(seed) for seed in range(100)]
    assert all(e.placements["cube"].color == "red" and e.placements["decoy"].color != "red" for e in episodes)
    assert {e.placements["decoy"].color for e in episodes} == set(task.colors) - {"red"}
    assert all(e.instruction == "reach the red cube" for e in episodes)
    sides = {e.placements["cube"].y > e.placements["decoy"].y for e in episodes}
    assert sides == {True, False}  # either cube may stand left of the other
    w = SimWorld("reach_marked", small_config())
    w.reset(episode_seed(0, 1))
    _, _, actions, success = run_expert(w, episode_seed(0, 1))
    w.close()
    assert success and 10 <= len(actions) <= 40


def test_tasks_without_a_marked_colour_draw_as_before():
    """``pick_color`` changes nothing for the other tasks: their layouts and colours are kept."""
    assert TASKS["reach_solo"].sample(11).placements["cube"].color == "red"
    assert [p.color for p in TASKS["reach"].sample(4).placements.values()] == ["yellow", "red", "green"]
