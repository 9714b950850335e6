"""Policy evaluation under camera perturbation, in simulation.

:class:`PerturbedCameraEnv` is a Gymnasium environment of one task in which the named
external cameras are moved, once per episode, by one of three protocols (``EvalConfig.protocol``):

* ``"paper"`` (the default; the paper's RQ1 protocol): the perturbation that
  ``PaperSampler(level, seed=seed).sample(episode_index)`` draws, about the pivot of
  the two external cameras' nominal poses; levels none / small / medium / large / extreme;
* ``"vista"``: VISTA's samplers (:mod:`.vista`), levels ``small_perturb`` and ``arc_90deg``:
  ``VistaSampler(level, seed=seed).sample(episode_index)``, about the point each camera
  looks at in the scene layout;
* ``"fov"``: level ``zoom``, the camera kept in place with its focal length scaled by a factor
  drawn log-uniformly in :data:`FOV_RANGE` (another lens or a zoom, as LIBERO-plus and
  robosuite's camera randomisation vary it): ``PaperSampler("none", seed=seed,
  focal_scale=FOV_RANGE).sample(episode_index)``.

Observations use the recorded datasets' keys and the library's conventions, so a policy
trained on a recorded dataset runs unchanged:

* ``observation.images.<camera>``: (3, H, W) float32 tensor in [0, 1];
* ``observation.state``: (12,) float32 tensor;
* ``task``: the instruction string.

Actions are ``[x, y, z, yaw, gripper]`` (see :mod:`.control`). An episode terminates on
success (reward 1) or is truncated after the task's step budget. Besides success,
:func:`evaluate` records how far each episode got (closest pinch-to-pick distance, whether
the pick was lifted), which separates policies that are still far from succeeding.

Example (``my_policy``: any ``policy(obs) -> action``)::

    env = PerturbedCameraEnv(EvalConfig(task="pick_place", level="large"))
    evaluate(my_policy, env, episodes=20).success_rate
    vista = PerturbedCameraEnv(EvalConfig(task="pick_place", level="arc_90deg", protocol="vista"))
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar

import gymnasium as gym
import numpy as np
import torch

from gensplat_transforms.data.format import IMAGE_KEY_PREFIX
from gensplat_transforms.views.perturbation import PaperSampler, Perturbation, pivot_point

from .control import ACTION_HIGH, ACTION_LOW
from .scene import mat_to_quat
from .tasks import episode_seed
from .vista import VistaSampler
from .world import CAMERA_NAMES, EXTERNAL_CAMERAS, STATE_NAMES, SimWorld, WorldConfig

_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


@dataclass
class EvalConfig:
    """Attributes:
    task: task name.
    level: perturbation level: with protocol "paper" none / small / medium / large / extreme
        (or any key of LEVELS), with "vista" small_perturb / arc_90deg, with "fov" zoom.
    perturbed: external cameras that are moved (each by the same perturbation).
    seed: seeds the episode layouts (evaluation stream, disjoint from recording) and the perturbations.
    max_steps: step budget per episode (default: the task's).
    world: scene settings; keep the camera layout of the training data.
    protocol: "paper" (default), "vista" or "fov"; see the module docstring.
    """

    task: str = "pick_place"
    level: str = "none"
    perturbed: tuple[str, ...] = ("left",)
    seed: int = 0
    max_steps: int | None = None
    world: WorldConfig = field(default_factory=WorldConfig)
    protocol: str = "paper"


PROTOCOLS = ("paper", "vista", "fov")
#: the "fov" protocol's range of focal-length factors
FOV_RANGE = (0.8, 1.25)


class PerturbedCameraEnv(gym.Env):
    """One task with perturbed external cameras; see the module docstring."""

    metadata: ClassVar[dict] = {"render_modes": []}

    def __init__(self, config: EvalConfig | None = None) -> None:
        self.config = config or EvalConfig()
        bad = [c for c in self.config.perturbed if c not in EXTERNAL_CAMERAS]
        if bad:
            raise ValueError(f"only external cameras {EXTERNAL_CAMERAS} can be perturbed, got {bad}")
        if self.config.protocol not in PROTOCOLS:
            raise ValueError(f"unknown evaluation protocol {self.config.protocol!r}, choose from {PROTOCOLS}")
        protocol = self.config.protocol
        paper = protocol != "vista"  # the fov protocol keeps the paper's pivot (it moves nothing)
        if protocol == "fov" and self.config.level != "zoom":
            raise ValueError(f"the fov protocol has one level, 'zoom', got {self.config.level!r}")
        self.sampler = (VistaSampler(self.config.level, seed=self.config.seed) if protocol == "vista" else
                        PaperSampler("none" if protocol == "fov" else self.config.level, seed=self.config.seed,
                                            focal_scale=FOV_RANGE if protocol == "fov" else (1.0, 1.0)))  # fmt: skip
        self.world = SimWorld(self.config.task, self.config.world)
        self.max_steps = self.config.max_steps or self.world.task.max_steps
        nominal = self.world.cameras(EXTERNAL_CAMERAS)
        self.nominal_c2w = dict(zip(EXTERNAL_CAMERAS, nominal.c2w))
        self.pivot = pivot_point(nominal.c2w[0], nominal.c2w[1])
        # the point each camera is moved about: the pivot, or (VISTA) the point it looks at
        external = self.config.world.scene.external
        self.centre = {n: self.pivot if paper else torch.tensor(external[n].target, dtype=torch.float64)
                       for n in EXTERNAL_CAMERAS}  # fmt: skip
        self.nominal_fovy = {n: float(self.world.model.cam_fovy[self.world.model.camera(n).id]) for n in EXTERNAL_CAMERAS}
        self.perturbation = Perturbation()
        self.episode_index = -1
        self._steps = 0
        h, w = self.world.config.height, self.world.config.width
        self.observation_space = gym.spaces.Dict(
            {
                **{
                    IMAGE_KEY_PREFIX + n: gym.spaces.Box(0.0, 1.0, (3, h, w), np.float32)
                    for n in CAMERA_NAMES
                },
                "observation.state": gym.spaces.Box(-np.inf, np.inf, (len(STATE_NAMES),), np.float32),
            }
        )
        self.action_space = gym.spaces.Box(ACTION_LOW.astype(np.float32), ACTION_HIGH.astype(np.float32))

    def _place_camera(self, name: str, c2w: torch.Tensor) -> None:
        """Move a world-fixed camera to an OpenCV camera-to-world pose."""
        cam = self.world.model.camera(name).id
        self.world.model.cam_pos[cam] = c2w[:3, 3].numpy()
        self.world.model.cam_quat[cam] = mat_to_quat(c2w[:3, :3].numpy() @ _GL_TO_CV)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start the next evaluation episode (or ``options["episode_index"]``)."""
        super().reset(seed=seed)
        self.episode_index = int((options or {}).get("episode_index", self.episode_index + 1))
        self.perturbation = self.sampler.sample(self.episode_index)
        for name in EXTERNAL_CAMERAS:
            c2w = self.nominal_c2w[name]
            moved = name in self.config.perturbed
            self._place_camera(name, self.perturbation.apply(c2w, self.centre[name]) if moved else c2w)
            scale = getattr(self.perturbation, "focal_scale", 1.0) if moved else 1.0
            fovy = self.nominal_fovy[name]  # vertical; f = (H / 2) / tan(fovy / 2)
            self.world.model.cam_fovy[self.world.model.camera(name).id] = fovy if scale == 1.0 else \
                math.degrees(2 * math.atan(math.tan(math.radians(fovy) / 2) / scale))  # fmt: skip
        episode = self.world.reset(episode_seed(self.config.seed, self.episode_index, "eval"))
        self._steps = 0
        info = {
            "episode_index": self.episode_index,
            "perturbation": self.perturbation.as_dict(),
            "instruction": episode.instruction,
        }
        return self._observation(), info

    def step(self, action):
        self.world.step(np.asarray(action, dtype=np.float64).reshape(-1))
        self._steps += 1
        success = self.world.success()
        return (
            self._observation(),
            float(success),
            success,
            self._steps >= self.max_steps,
            {"success": success},
        )

    def _observation(self) -> dict:
        frames = self.world.render(CAMERA_NAMES, depth=False)
        obs = {
            IMAGE_KEY_PREFIX + n: torch.from_numpy(frames[n][0]).permute(2, 0, 1).float() / 255
            for n in CAMERA_NAMES
        }
        obs["observation.state"] = torch.from_numpy(self.world.robot_state())
        obs["task"] = self.world.episode.instruction
        return obs

    def close(self) -> None:
        self.world.close()


#: The pick counts as lifted once its centre rose this far (m) above where it started.
LIFT_HEIGHT = 0.03


@dataclass
class EvalResult:
    """Per episode: success, steps, the perturbation, the closest the pinch point came to the
    pick object's centre (to the reach goal in a reach task) (m) and whether the pick was
    lifted by :data:`LIFT_HEIGHT`."""

    level: str
    successes: list[bool] = field(default_factory=list)
    steps: list[int] = field(default_factory=list)
    perturbations: list[dict] = field(default_factory=list)
    reach_m: list[float] = field(default_factory=list)
    lifted: list[bool] = field(default_factory=list)

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else 0.0

    @property
    def lift_rate(self) -> float:
        return float(np.mean(self.lifted)) if self.lifted else 0.0


def evaluate(
    policy: Callable[[dict], np.ndarray | torch.Tensor],
    env: PerturbedCameraEnv,
    episodes: int = 10,
    reset: Callable[[], None] | None = None,
) -> EvalResult:
    """Run evaluation episodes 0 .. ``episodes - 1`` of ``policy`` in ``env`` and report success.

    torch's global generator is seeded at the start of every episode (``episode_seed(seed,
    i, "policy")``), so a stochastic policy (a diffusion policy's sampling noise) gives the
    same result when evaluated again, and every policy meets the same noise in episode i.

    Args:
        policy: maps an observation (see the module docstring) to a (5,) action.
        reset: called after every environment reset (e.g. a LeRobot policy's ``reset``).
    """
    result = EvalResult(env.config.level)
    task = env.world.task
    for i in range(episodes):
        obs, info = env.reset(options={"episode_index": i})
        torch.manual_seed(episode_seed(env.config.seed, i, "policy"))
        if reset is not None:
            reset()
        start_z = env.world.object_positions()[task.pick][2]
        done, steps, success, reach, lifted = False, 0, False, np.inf, False
        while not done:
            action = policy(obs)
            obs, _, success, truncated, _ = env.step(torch.as_tensor(action).detach().cpu().numpy())
            steps += 1
            done = success or truncated
            pick = env.world.object_positions()[task.pick]
            goal = pick if task.place is not None else task.reach_goal(pick)
            reach = min(reach, float(np.linalg.norm(env.world.ee_pose()[0] - goal)))
            lifted = lifted or pick[2] - start_z > LIFT_HEIGHT
        result.successes.append(bool(success))
        result.steps.append(steps)
        result.perturbations.append(info["perturbation"])
        result.reach_m.append(reach)
        result.lifted.append(bool(lifted))
    return result


def paired_difference(a: list[bool], b: list[bool], resamples: int = 10000, seed: int = 0) -> dict:
    """Success of ``b`` minus success of ``a`` on the same episodes (same layouts,
    perturbations and sampling noise), in percentage points.

    Returns {"points", "ci95" (paired bootstrap over episodes), "a_only" / "b_only" (episodes
    only that one solved), "mcnemar_p" (exact two-sided McNemar test on those discordant
    episodes: the chance of a split at least this uneven if both policies were equal; three
    significant digits, never rounded to 0)}.
    """
    if len(a) != len(b) or not a:
        raise ValueError(f"paired_difference: need two equal, non-empty lists, got {len(a)} and {len(b)}")
    d = np.asarray(b, dtype=np.float64) - np.asarray(a, dtype=np.float64)
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, len(d), size=(resamples, len(d)))].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    a_only, b_only = int((d < 0).sum()), int((d > 0).sum())
    n, k = a_only + b_only, min(a_only, b_only)
    p = min(1.0, 2 * sum(math.comb(n, j) for j in range(k + 1)) / 2**n) if n else 1.0
    return {"points": round(100 * float(d.mean()), 2), "ci95": [round(100 * float(lo), 2), round(100 * float(hi), 2)],
            "a_only": a_only, "b_only": b_only, "mcnemar_p": float(f"{p:.3g}")}  # fmt: skip
