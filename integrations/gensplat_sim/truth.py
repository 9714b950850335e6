"""Ground truth for recorded simulated datasets: re-create any recorded timestep and render
it from any camera.

A recorded dataset carries its simulation sidecar beside LeRobot's files:

* ``<root>/sim/world.json``: ``{"format": "gensplat-sim", "format_version": "1",
  "task": name, "world": WorldConfig.to_dict(), "sensor_depth": SensorDepthConfig as a dict,
  or null for exact depth}``;
* ``<root>/sim/episode_{episode_index:06d}.safetensors``: float64 tensors ``qpos`` (T, nq),
  ``qvel`` (T, nv) and ``ctrl`` (T, nu), the full MuJoCo state observed at every frame,
  with metadata ``{"episode": EpisodeSpec JSON (seed, layout, colours, instruction)}``.

Example (a recorded dataset at ``root``, a ``pivot``)::

    truth = GroundTruth(root)
    cams = truth.cameras(episode_index=0, frame_index=10, names=("left",))
    moved = cams.with_c2w(Perturbation("y", 20.0, 0.04).apply(cams.c2w, pivot))
    rgb, depth = truth.render(0, 10, moved)            # (1, 3, H, W), (1, 1, H, W)
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.numpy import save_file

from gensplat_transforms.core.atomic import atomic_write, atomic_write_json
from gensplat_transforms.core.cameras import Cameras

from .sensor import SensorDepthConfig
from .tasks import EpisodeSpec
from .world import CAMERA_NAMES, SimState, SimWorld, WorldConfig

SIM_FORMAT = "gensplat-sim"
SIM_FORMAT_VERSION = "1"


def sim_episode_path(root: str | os.PathLike, episode_index: int) -> Path:
    return Path(root) / "sim" / f"episode_{int(episode_index):06d}.safetensors"


def save_world(
    root: str | os.PathLike, world: SimWorld, sensor_depth: SensorDepthConfig | None = None
) -> None:
    """Write ``sim/world.json`` (task, world configuration and the depth sensor model)."""
    doc = {
        "format": SIM_FORMAT,
        "format_version": SIM_FORMAT_VERSION,
        "task": world.task.name,
        "world": world.config.to_dict(),
        "sensor_depth": None if sensor_depth is None else asdict(sensor_depth),
    }
    atomic_write_json(Path(root) / "sim" / "world.json", doc)


def save_sim_episode(
    root: str | os.PathLike, episode_index: int, episode: EpisodeSpec, states: list[SimState]
) -> None:
    """Write one episode's per-frame simulation states."""
    tensors = {
        k: np.stack([getattr(s, k) for s in states]).astype(np.float64) for k in ("qpos", "qvel", "ctrl")
    }
    meta = {"episode": json.dumps(episode.to_dict())}
    atomic_write(sim_episode_path(root, episode_index), lambda tmp: save_file(tensors, tmp, metadata=meta))


def load_sim_episode(root: str | os.PathLike, episode_index: int) -> tuple[EpisodeSpec, list[SimState]]:
    """The episode spec and the per-frame states written by :func:`save_sim_episode`."""
    path = sim_episode_path(root, episode_index)
    if not path.is_file():
        raise FileNotFoundError(f"no simulation sidecar for episode {episode_index}: {path}")
    with safe_open(str(path), framework="np") as f:
        episode = EpisodeSpec.from_dict(json.loads(f.metadata()["episode"]))
        qpos, qvel, ctrl = (f.get_tensor(k) for k in ("qpos", "qvel", "ctrl"))
    return episode, [SimState(*s) for s in zip(qpos, qvel, ctrl)]


class GroundTruth:
    """Re-creates the timesteps of a recorded simulated dataset.

    Args:
        root: the dataset root (with its ``sim/`` sidecar).
        config: override the recorded world configuration (e.g. another image size or
            shadows on); camera layout and textures should stay as recorded.
    """

    def __init__(self, root: str | os.PathLike, config: WorldConfig | None = None) -> None:
        self.root = Path(root)
        doc = json.loads((self.root / "sim" / "world.json").read_text())
        if doc.get("format") != SIM_FORMAT or doc.get("format_version") != SIM_FORMAT_VERSION:
            raise ValueError(
                f"{self.root / 'sim' / 'world.json'}: not a {SIM_FORMAT} v{SIM_FORMAT_VERSION} file"
            )
        self.world = SimWorld(doc["task"], config or WorldConfig.from_dict(doc["world"]))
        self._episode: tuple[int, EpisodeSpec, list[SimState]] | None = None

    def num_frames(self, episode_index: int) -> int:
        return len(self._load(episode_index)[1])

    def _load(self, episode_index: int) -> tuple[EpisodeSpec, list[SimState]]:
        if self._episode is None or self._episode[0] != episode_index:
            self._episode = (episode_index, *load_sim_episode(self.root, episode_index))
        return self._episode[1], self._episode[2]

    def set_timestep(self, episode_index: int, frame_index: int) -> SimWorld:
        """Put the world in the recorded state of a frame (colours included) and return it."""
        episode, states = self._load(episode_index)
        if not 0 <= frame_index < len(states):
            raise IndexError(
                f"episode {episode_index} has {len(states)} frames, asked for frame {frame_index}"
            )
        if self.world.episode != episode:
            self.world.set_episode(episode)
        self.world.set_state(states[frame_index])
        return self.world

    def cameras(self, episode_index: int, frame_index: int, names: tuple[str, ...] = CAMERA_NAMES) -> Cameras:
        """The named cameras as they were at that frame (the wrist camera moves)."""
        return self.set_timestep(episode_index, frame_index).cameras(names)

    def render(
        self, episode_index: int, frame_index: int, cameras: Cameras
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """True RGB (B, 3, H, W) in [0, 1] and metric depth (B, 1, H, W) of a recorded frame seen
        from any OpenCV cameras (see :meth:`SimWorld.render_at` for the intrinsics allowed)."""
        return self.set_timestep(episode_index, frame_index).render_at(cameras)

    def close(self) -> None:
        self.world.close()
