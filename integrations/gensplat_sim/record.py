"""Record scripted demonstrations into a local LeRobotDataset (v3, offline).

Each attempt first runs the expert without rendering; successful episodes are then replayed
state by state and rendered, so the recorded images are exactly what
:class:`~.truth.GroundTruth` re-renders. Failed attempts are skipped (and counted).

Dataset contents (see :mod:`gensplat_transforms.data.format` for calibration and depth):

* ``observation.images.{left,right,wrist}``: (H, W, 3) RGB, calibration in ``info`` (see
  :mod:`gensplat_transforms.data.format`);
* ``observation.state``: (12,) float32, names :data:`~.world.STATE_NAMES`;
* ``action``: (5,) float32 ``[x, y, z, yaw, gripper]`` (see :mod:`.control`);
* ``task``: the instruction, e.g. "put the red cube on the blue plate";
* ``depth/<left|right>/episode_*.safetensors`` and ``sim/`` sidecars: the exact rendered
  depth, or with ``RecordConfig.sensor_depth`` set the depth a real RGB-D camera would give
  (:mod:`.sensor`; seeded by the episode seed, recorded in ``sim/world.json``).
"""

from __future__ import annotations

import os
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import torch
from tqdm import tqdm

from gensplat_transforms.core.config_flags import add_flags, config_from_flags, flag, nested
from gensplat_transforms.data.format import IMAGE_KEY_PREFIX, camera_info, save_depth
from gensplat_transforms.data.outputs import new_folder

from .control import ACTION_NAMES
from .experts import ExpertConfig, run_expert
from .sensor import SensorDepthConfig, sensor_depth
from .tasks import episode_seed
from .truth import save_sim_episode, save_world
from .world import CAMERA_NAMES, EXTERNAL_CAMERAS, STATE_NAMES, SimWorld, WorldConfig

#: least image side of MP4 video: LeRobot's AV1 encoder (libsvtav1) kills the process below 25 px
#: wide and refuses images under 4 px high; PNG images need 2 px
MIN_VIDEO_SIDE, MIN_IMAGE_SIDE = 32, 2
#: most frames per second: the physics rate (each control step takes at least one physics step)
MAX_FPS = 500


@dataclass
class RecordConfig:
    """Attributes:
    root: output folder (must not exist yet).
    task: task name (``pick_place`` or ``stack``).
    episodes: number of successful demonstrations to record.
    seed: run seed; attempt k uses ``episode_seed(seed, k)``.
    use_videos: store images as MP4 video (LeRobot's default) or as PNG images (lossless).
    repo_id: LeRobot repo id written into the metadata (default ``gensplat/sim_<task>``).
    max_attempts: give up after this many expert attempts (default ``2 * episodes + 10``).
    max_frames: keep only the first ``max_frames`` timesteps of each demonstration (short clips,
        e.g. for tests at a large image size); None (default) keeps them all.
    world, expert: scene and expert settings.
    sensor_depth: record the external cameras' depth as this simulated sensor measures it
        (:mod:`.sensor`); None (default) records the exact depth.
    """

    # the flags of ``gensplat record`` (:func:`add_record_flags`)
    root: Path = field(metadata=flag("dataset root to create (must not exist)", flag="--out", type=Path))
    task: str = field(default="pick_place", metadata=flag("pick_place or stack"))
    episodes: int = field(default=10, metadata=flag("demonstrations to record"))
    seed: int = field(default=0, metadata=flag("run seed"))
    use_videos: bool = field(default=True, metadata=flag(
        "store lossless PNG images (default: MP4 video, LeRobot's default)", flag="--images", action="store_false"))
    repo_id: str | None = None
    max_attempts: int | None = None
    max_frames: int | None = None
    world: WorldConfig = field(default_factory=WorldConfig, metadata=nested())
    expert: ExpertConfig = field(default_factory=ExpertConfig)
    sensor_depth: SensorDepthConfig | None = field(default=None, metadata=flag(
        "record depth as a RealSense D435 measures it (noise, holes, 1 mm steps, 1 px shift)",
        action="store_const", const=SensorDepthConfig()))  # fmt: skip


@dataclass
class RecordResult:
    root: Path
    episodes: int
    attempts: int
    frames: int
    seconds: float

    @property
    def success_rate(self) -> float:
        return self.episodes / max(self.attempts, 1)

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(self.seconds, 1e-9)


def dataset_features(world: SimWorld, use_videos: bool) -> dict:
    """LeRobot feature spec of a simulated dataset, calibration included."""
    h, w = world.config.height, world.config.width
    cams = world.cameras(CAMERA_NAMES)
    features = {}
    for i, name in enumerate(CAMERA_NAMES):
        external = name in EXTERNAL_CAMERAS
        features[IMAGE_KEY_PREFIX + name] = {
            "dtype": "video" if use_videos else "image",
            "shape": (h, w, 3),
            "names": ["height", "width", "channels"],
            "info": camera_info(
                cams.K[i], cams.c2w[i] if external else None, "external" if external else "wrist"
            ),
        }
    features["observation.state"] = {
        "dtype": "float32",
        "shape": (len(STATE_NAMES),),
        "names": list(STATE_NAMES),
    }
    features["action"] = {"dtype": "float32", "shape": (len(ACTION_NAMES),), "names": list(ACTION_NAMES)}
    return features


def _check_config(config: RecordConfig) -> None:
    """Raise ``ValueError`` saying what to change when ``config`` cannot be recorded."""
    low, kind = (MIN_VIDEO_SIDE, "MP4 video") if config.use_videos else (MIN_IMAGE_SIDE, "PNG images")
    for name, side in (("height", config.world.height), ("width", config.world.width)):
        if side < low:
            note = f" (PNG images, --images, store sides down to {MIN_IMAGE_SIDE} px)" if config.use_videos else ""
            raise ValueError(f"image {name} {side} px: at least {low} px per side for {kind}{note}")
    if not 1 <= config.world.fps <= MAX_FPS:
        raise ValueError(f"fps {config.world.fps}: give 1 to {MAX_FPS} frames per second (the physics rate)")
    if config.episodes < 1:
        raise ValueError(f"episodes {config.episodes}: give at least 1")


def record(config: RecordConfig, progress: bool = True) -> RecordResult:
    """Record ``config.episodes`` successful expert demonstrations into the new folder
    ``config.root`` (see the module docstring), which is removed again when recording fails.
    Raises ``ValueError`` when ``config.root`` exists or a setting cannot be recorded."""
    _check_config(config)
    with new_folder(config.root) as root:
        return _record(config, root, progress)


@contextmanager
def kept_scheduling():
    """Run the block, then give the calling thread back the scheduling policy and priority it
    had. LeRobot's AV1 encoder (SVT-AV1) run by root makes the thread that encodes a real-time
    (``SCHED_FIFO``, priority 99) thread, which would then starve every other process of the
    machine for the rest of the run."""
    if not hasattr(os, "sched_getscheduler"):  # not on this platform
        yield
        return
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        yield
    finally:
        if (os.sched_getscheduler(0), os.sched_getparam(0)) != (policy, param):
            os.sched_setscheduler(0, policy, param)  # lowering a priority needs no privilege


def _record(config: RecordConfig, root: Path, progress: bool) -> RecordResult:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    os.environ.setdefault("SVT_LOG", "1")  # AV1 encoder: errors only
    from gensplat_lerobot import video_backend
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    world = SimWorld(config.task, config.world)
    dataset = LeRobotDataset.create(
        repo_id=config.repo_id or f"gensplat/sim_{world.task.name}",
        fps=world.config.fps,
        features=dataset_features(world, config.use_videos),
        root=root,
        robot_type="franka_panda_robotiq_2f85",
        use_videos=config.use_videos,
        image_writer_threads=4,
        video_backend=video_backend(),
    )
    save_world(root, world, config.sensor_depth)
    intrinsics = world.cameras(EXTERNAL_CAMERAS).K
    max_attempts = config.max_attempts or 2 * config.episodes + 10
    saved = attempts = frames = 0
    start = time.perf_counter()
    bar = tqdm(total=config.episodes, unit="episode", desc=f"record {world.task.name}", disable=not progress)
    try:
        while saved < config.episodes and attempts < max_attempts:
            episode, states, actions, success = run_expert(
                world, episode_seed(config.seed, attempts), config.expert
            )
            attempts += 1
            if not success:
                continue
            states, actions = states[: config.max_frames], actions[: config.max_frames]
            depth = {name: [] for name in EXTERNAL_CAMERAS}
            noise = torch.Generator().manual_seed(episode.seed)
            for state, action in zip(states, actions):
                world.set_state(state)
                rendered = world.render(CAMERA_NAMES, depth=True)
                frame = {IMAGE_KEY_PREFIX + n: rendered[n][0] for n in CAMERA_NAMES}
                frame.update(
                    {"observation.state": world.robot_state(), "action": action, "task": episode.instruction}
                )
                dataset.add_frame(frame)
                for name, K in zip(EXTERNAL_CAMERAS, intrinsics):
                    rgb, z = (torch.from_numpy(a) for a in rendered[name])
                    if config.sensor_depth is not None:
                        z = sensor_depth(z, rgb.permute(2, 0, 1) / 255.0, K, config.sensor_depth, noise)
                    depth[name].append(z)
            with kept_scheduling():
                dataset.save_episode(parallel_encoding=False)  # no fork() of this multi-threaded GL process
            for name in EXTERNAL_CAMERAS:
                save_depth(root, name, saved, torch.stack(depth[name]))
            save_sim_episode(root, saved, episode, states)
            saved += 1
            frames += len(states)
            bar.update(1)
            bar.set_postfix(
                frames=frames,
                fps=f"{frames / (time.perf_counter() - start):.1f}",
                success=f"{saved}/{attempts}",
            )
    finally:
        bar.close()
        with kept_scheduling():
            dataset.finalize()
        world.close()
    if saved < config.episodes:
        raise RuntimeError(f"only {saved} of {config.episodes} episodes succeeded in {attempts} attempts")
    return RecordResult(root, saved, attempts, frames, time.perf_counter() - start)


def add_record_flags(parser) -> None:
    """``gensplat record``'s flags: :class:`RecordConfig`'s and :class:`.world.WorldConfig`'s
    fields that have one, and ``--size``, the side of square images."""
    add_flags(parser, RecordConfig)
    side = WorldConfig.__dataclass_fields__["height"].default
    parser.add_argument("--size", type=int, default=side, help=f"square image side in pixels (default: {side})")


def record_from_cli(args) -> RecordResult:
    """``gensplat record``: build the config from parsed arguments, record, print a summary."""
    world = config_from_flags(args, WorldConfig, height=args.size if args.height is None else args.height,
                              width=args.size if args.width is None else args.width, reflections=args.shadows)
    config = config_from_flags(args, RecordConfig, world=world)
    result = record(config)
    print(
        f"recorded {result.episodes} {args.task} episode(s), {result.frames} frames, into {result.root} "
        f"(expert success {result.episodes}/{result.attempts}, {result.frames_per_second:.1f} frames/s)"
    )
    return result
