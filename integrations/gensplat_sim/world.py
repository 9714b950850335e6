"""The simulated Franka tabletop: physics, end-effector control, calibrated cameras and
rendering (RGB, metric depth, segmentation) at the dataset cameras or at any pose.

``MUJOCO_GL`` must name a headless backend before MuJoCo is imported; importing
:mod:`gensplat_sim` sets it to ``egl`` (Mesa llvmpipe on a CPU) unless it is set.

Example:
    >>> world = SimWorld("pick_place")
    >>> episode = world.reset(seed=0)           # random layout and colours
    >>> frames = world.render()                 # {"left": (rgb, depth), "right": ..., "wrist": ...}
    >>> world.step(np.array([0.5, 0.0, 0.2, 0.0, 0.0]))   # [x, y, z, yaw, gripper]
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import mujoco
import numpy as np
import torch

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.config_flags import flag

from .control import ArmController, yaw_of
from .render import OffscreenRenderer
from .scene import HOME_QPOS, CameraSpec, SceneConfig, build_model
from .tasks import PALETTE, EpisodeSpec, Task, get_task

CAMERA_NAMES = ("left", "right", "wrist")
EXTERNAL_CAMERAS = ("left", "right")
STATE_NAMES = ("ee_x", "ee_y", "ee_z", "ee_yaw", "gripper") + tuple(f"joint{i}" for i in range(1, 8))
_GRIPPER_JOINT = "left_driver_joint"
_GRIPPER_CLOSED_QPOS = 0.8
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


@dataclass
class WorldConfig:
    """Attributes:
    height, width: image size of every camera.
    fps: control (and recording) frequency; physics runs at 500 Hz underneath.
    shadows, reflections: MuJoCo's shadow and reflection passes (off: ~5x faster on a CPU).
    scene: camera placements and textures.
    """

    # flags of ``gensplat record`` (:mod:`gensplat_transforms.core.config_flags`); its --size sets
    # both sides, --shadows both passes
    height: int = field(default=224, metadata=flag("image height in pixels", default=None, shown="--size"))
    width: int = field(default=224, metadata=flag("image width in pixels", default=None, shown="--size"))
    fps: int = field(default=10, metadata=flag("control and recording rate"))
    shadows: bool = field(default=False, metadata=flag("render shadows and reflections (slower)",
                                                       action="store_true"))
    reflections: bool = False
    scene: SceneConfig = field(default_factory=SceneConfig)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> WorldConfig:
        d = dict(d)
        scene = dict(d.pop("scene"))
        scene["external"] = {
            k: CameraSpec(tuple(v["eye"]), tuple(v["target"]), v["fovy"])
            for k, v in scene["external"].items()
        }
        return cls(**d, scene=SceneConfig(**scene))


@dataclass
class SimState:
    """Full simulation state at one timestep: (nq,) positions, (nv,) velocities, (nu,) controls."""

    qpos: np.ndarray
    qvel: np.ndarray
    ctrl: np.ndarray


class SimWorld:
    """One task's scene with its controller and renderers.

    Args:
        task: task name (see :data:`~.tasks.TASKS`) or a :class:`~.tasks.Task`.
        config: image size, control rate, render options, camera layout.
    """

    def __init__(self, task: str | Task = "pick_place", config: WorldConfig | None = None) -> None:
        self.task = get_task(task)
        self.config = config or WorldConfig()
        self.model = build_model(list(self.task.objects), self.config.scene)
        self.data = mujoco.MjData(self.model)
        self.controller = ArmController(self.model, np.array(HOME_QPOS))
        self.substeps = round(1.0 / (self.config.fps * self.model.opt.timestep))
        self.episode: EpisodeSpec | None = None
        self._renderers: dict[tuple[int, int], OffscreenRenderer] = {}
        self._probe = self.model.camera("probe").id
        self._gripper_adr = self.model.joint(_GRIPPER_JOINT).qposadr[0]
        self.data.qpos[:7] = self.data.ctrl[:7] = HOME_QPOS
        mujoco.mj_forward(self.model, self.data)  # valid camera poses before the first episode

    # ------------------------------------------------------------------ episodes and physics
    def reset(self, seed: int) -> EpisodeSpec:
        """Start the episode drawn from ``seed``: robot at home, objects placed, colours set."""
        episode = self.task.sample(seed)
        self.set_episode(episode)
        return episode

    def set_episode(self, episode: EpisodeSpec) -> None:
        """Apply an episode's colours and initial layout (the state at frame 0)."""
        if episode.task != self.task.name:
            raise ValueError(f"episode is for task {episode.task!r}, this world runs {self.task.name!r}")
        self.episode = episode
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:7] = d.ctrl[:7] = HOME_QPOS
        for obj in self.task.objects:
            p = episode.placements[obj.name]
            adr = m.joint(obj.name).qposadr[0]
            d.qpos[adr : adr + 3] = (p.x, p.y, obj.half_height)
            d.qpos[adr + 3 : adr + 7] = (math.cos(p.yaw / 2), 0.0, 0.0, math.sin(p.yaw / 2))
            m.geom_rgba[m.geom(obj.name).id] = (*PALETTE[p.color], 1.0)
        mujoco.mj_forward(m, d)

    def step(self, action: np.ndarray) -> None:
        """Apply one ``[x, y, z, yaw, gripper]`` action for ``1 / fps`` seconds."""
        self.controller.apply(self.data, action)
        mujoco.mj_step(self.model, self.data, nstep=self.substeps)

    def get_state(self) -> SimState:
        d = self.data
        return SimState(d.qpos.copy(), d.qvel.copy(), d.ctrl.copy())

    def set_state(self, state: SimState) -> None:
        d = self.data
        d.qpos[:], d.qvel[:], d.ctrl[:] = state.qpos, state.qvel, state.ctrl
        mujoco.mj_forward(self.model, d)

    def object_positions(self) -> dict[str, np.ndarray]:
        """World centre (3,) of every object."""
        return {o.name: self.data.body(o.name).xpos.copy() for o in self.task.objects}

    def success(self) -> bool:
        """The task's success test on the current state."""
        return self.task.success(
            self.object_positions(), gripper_closed=self.data.ctrl[7] > 127.5, pinch=self.ee_pose()[0]
        )

    def ee_pose(self) -> tuple[np.ndarray, float]:
        """Pinch-site position (3,) and yaw (radians)."""
        site = self.data.site("pinch")
        return site.xpos.copy(), yaw_of(site.xmat.reshape(3, 3))

    def robot_state(self) -> np.ndarray:
        """(12,) float32 proprioception, named by :data:`STATE_NAMES`: pinch position, yaw,
        gripper closure in [0, 1] and the seven joint angles."""
        pos, yaw = self.ee_pose()
        grip = np.clip(self.data.qpos[self._gripper_adr] / _GRIPPER_CLOSED_QPOS, 0.0, 1.0)
        return np.concatenate([pos, [yaw, grip], self.data.qpos[:7]]).astype(np.float32)

    # ------------------------------------------------------------------ cameras and rendering
    def renderer(self, height: int | None = None, width: int | None = None) -> OffscreenRenderer:
        """The (cached) renderer for an image size (default: the config's)."""
        key = (height or self.config.height, width or self.config.width)
        if key not in self._renderers:
            self._renderers[key] = OffscreenRenderer(
                self.model, *key, self.config.shadows, self.config.reflections
            )
        return self._renderers[key]

    def cameras(self, names: tuple[str, ...] = CAMERA_NAMES) -> Cameras:
        """Calibrated OpenCV cameras (float64) at their current poses (the wrist one moves)."""
        ids = [self.model.camera(n).id for n in names]
        return Cameras.from_mujoco(
            torch.from_numpy(self.data.cam_xpos[ids].copy()),
            torch.from_numpy(self.data.cam_xmat[ids].copy()),
            torch.from_numpy(self.model.cam_fovy[ids].copy()),
            self.config.width,
            self.config.height,
        )

    def render(
        self, names: tuple[str, ...] = CAMERA_NAMES, depth: bool = True
    ) -> dict[str, tuple[np.ndarray, np.ndarray | None]]:
        """RGB (H, W, 3) uint8 and metric depth (H, W) float32 (0 = invalid) per named camera."""
        r = self.renderer()
        return {n: r.render(self.data, self.model.camera(n).id, depth) for n in names}

    def render_at(self, cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
        """Render the current state from arbitrary OpenCV cameras.

        Args:
            cameras: B cameras with square pixels and a centred principal point (MuJoCo's
                pinhole model: f = (H / 2) / tan(fovy / 2), c = (W / 2, H / 2)).
        Returns:
            rgb: (B, 3, H, W) float32 in [0, 1]; depth: (B, 1, H, W) float32 metric z, 0 = invalid.
        """
        K = cameras.K.double()
        w, h = cameras.width, cameras.height
        centred = torch.allclose(
            K[:, 0, 2], torch.full_like(K[:, 0, 2], w / 2), atol=1e-3
        ) and torch.allclose(K[:, 1, 2], torch.full_like(K[:, 1, 2], h / 2), atol=1e-3)
        if not centred or not torch.allclose(K[:, 0, 0], K[:, 1, 1], rtol=1e-6):
            raise ValueError("render_at: MuJoCo renders square pixels with a centred principal point only")
        r = self.renderer(h, w)
        rgbs, depths = [], []
        for K_i, c2w in zip(K, cameras.c2w.double()):
            R = c2w[:3, :3].numpy() @ _GL_TO_CV
            self.data.cam_xpos[self._probe] = c2w[:3, 3].numpy()
            self.data.cam_xmat[self._probe] = R.reshape(-1)
            self.model.cam_fovy[self._probe] = math.degrees(2 * math.atan(h / 2 / float(K_i[1, 1])))
            rgb, depth = r.render(self.data, self._probe)
            rgbs.append(torch.from_numpy(rgb).permute(2, 0, 1).float() / 255)
            depths.append(torch.from_numpy(depth)[None])
        return torch.stack(rgbs), torch.stack(depths)

    def segmentation(self, name: str) -> np.ndarray:
        """(H, W) int32 geom id per pixel of a named camera (-1 = nothing); see ``model.geom(id).name``."""
        return self.renderer().segmentation(self.data, self.model.camera(name).id)

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()
