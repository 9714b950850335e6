"""Scripted experts: a waypoint state machine that picks the task's ``pick`` object and puts
it on its ``place`` object, using the true object poses (privileged information).

Phases: approach above the object, descend, close, lift, carry above the place object,
lower, open, retreat. A reach task (no ``place``) stops after descending to the reach goal
and holding it for ``settle`` seconds. Each phase moves the commanded pinch target in a
straight line at a bounded speed, so consecutive actions differ by at most a few centimetres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .world import SimWorld


@dataclass
class ExpertConfig:
    """Attributes:
    speed: Cartesian speed of free moves (m/s); ``slow_speed`` near objects.
    hover: clearance above the objects while moving between them (m).
    grasp_wait, release_wait: seconds spent closing and opening the gripper.
    settle: seconds of idle actions after the retreat.
    """

    speed: float = 0.35
    slow_speed: float = 0.15
    hover: float = 0.10
    grasp_wait: float = 0.6
    release_wait: float = 0.4
    settle: float = 0.3


def _fold_yaw(yaw: float) -> float:
    """Equivalent grasp yaw of a square object in [-pi/4, pi/4] (90 degree symmetry)."""
    return (yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4


def _box_yaw(quat: np.ndarray) -> float:
    w, x, y, z = quat
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


class PickPlaceExpert:
    """Scripted expert for any :class:`~.tasks.Task` (pick onto place, or reach).

    Call :meth:`act` once per control step and pass the action to ``world.step``;
    :attr:`done` turns true after the retreat and settling time.
    """

    def __init__(self, world: SimWorld, config: ExpertConfig | None = None) -> None:
        self.world, self.cfg = world, config or ExpertConfig()
        self.dt = 1.0 / world.config.fps
        pos, yaw = world.ee_pose()
        self._target = np.array([*pos, yaw, 0.0])
        self._phases = iter(self._plan())
        self._segment: list[np.ndarray] = []
        self.done = False

    def _plan(self):
        """Yield (goal function, speed, hold seconds); goals are evaluated when a phase starts."""
        task, c = self.world.task, self.cfg
        pick_h = task.object(task.pick).half_height

        def pick_pose():
            body = self.world.data.body(task.pick)
            return body.xpos.copy(), _fold_yaw(_box_yaw(body.xquat))

        def above_pick(t):
            p, yaw = pick_pose()
            return np.array([p[0], p[1], p[2] + pick_h + c.hover, yaw, 0.0])

        def at_pick(t):
            p, yaw = pick_pose()
            return np.array([p[0], p[1], max(p[2], 0.015), yaw, 0.0])

        def place_xy():
            return self.world.data.body(task.place).xpos[:2].copy()

        yield above_pick, c.speed, 0.0
        if task.place is None:
            yield lambda t: np.r_[task.reach_goal(pick_pose()[0]), t[3], 0.0], c.slow_speed, c.settle
            return
        place_h = task.object(task.place).half_height
        carry_z = 2 * place_h + 2 * pick_h + c.hover
        yield at_pick, c.slow_speed, 0.0
        yield lambda t: np.r_[t[:4], 1.0], c.speed, c.grasp_wait
        yield lambda t: np.r_[t[:2], carry_z, t[3], 1.0], c.slow_speed, 0.0
        yield lambda t: np.r_[place_xy(), carry_z, t[3], 1.0], c.speed, 0.0
        yield lambda t: np.r_[place_xy(), 2 * place_h + pick_h + 0.005, t[3], 1.0], c.slow_speed, 0.0
        yield lambda t: np.r_[t[:4], 0.0], c.speed, c.release_wait
        yield lambda t: np.r_[t[:2], t[2] + c.hover, t[3], 0.0], c.speed, c.settle

    def _next_segment(self) -> bool:
        """Interpolate the next phase from the current target; False when the plan is done."""
        phase = next(self._phases, None)
        if phase is None:
            return False
        goal_fn, speed, hold = phase
        goal = goal_fn(self._target.copy())
        n = max(1, math.ceil(np.linalg.norm(goal[:3] - self._target[:3]) / (speed * self.dt)))
        self._segment = [self._target + (goal - self._target) * (i + 1) / n for i in range(n)]
        self._segment += [goal] * round(hold / self.dt)
        return True

    def act(self) -> np.ndarray:
        """The next action ``[x, y, z, yaw, gripper]`` (float32)."""
        while not self._segment:
            if not self._next_segment():
                self.done = True
                return self._target.astype(np.float32)
        self._target = self._segment.pop(0)
        return self._target.astype(np.float32)


def run_expert(world: SimWorld, seed: int, config: ExpertConfig | None = None, max_steps: int = 400):
    """Run one expert episode without rendering.

    Returns:
        (episode spec, states, actions, success): the :class:`~.world.SimState` observed
        before each action, the (T, 5) float32 actions, and the task's success at the end.
    """
    episode = world.reset(seed)
    expert = PickPlaceExpert(world, config)
    states, actions = [], []
    for _ in range(max_steps):
        action = expert.act()
        if expert.done:
            break
        states.append(world.get_state())
        actions.append(action)
        world.step(action)
    return episode, states, np.stack(actions), world.success()


class ExpertPolicy:
    """The scripted expert as a policy (privileged: it reads the true state of ``world``, not
    the observation); an upper bound for :func:`~.evaluate.evaluate`. Call :meth:`reset`
    after every environment reset."""

    def __init__(self, world: SimWorld, config: ExpertConfig | None = None) -> None:
        self.world, self.config = world, config
        self.expert: PickPlaceExpert | None = None

    def reset(self) -> None:
        self.expert = PickPlaceExpert(self.world, self.config)

    def __call__(self, observation: dict) -> np.ndarray:
        return self.expert.act()
