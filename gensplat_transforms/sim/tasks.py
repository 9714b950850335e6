"""Tabletop tasks: which objects a scene holds, how an episode is randomised, the instruction
string and success detection.

Every task is "move object ``pick`` onto object ``place``" with one distractor on the table:

* ``pick_place``: a 4 cm cube onto a plate;
* ``stack``: a 4 cm cube onto a 6 cm cube.

Per episode the object positions, yaws and colours are drawn from the episode seed; colours
come from a named palette, so the instruction can name them ("put the red cube on the blue
plate"), while the objects stay distinguishable by shape alone (for policies without language).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .scene import WORKSPACE_HIGH, WORKSPACE_LOW, ObjectSpec

PALETTE: dict[str, tuple[float, float, float]] = {
    "red": (0.85, 0.12, 0.10),
    "green": (0.15, 0.65, 0.20),
    "blue": (0.12, 0.30, 0.85),
    "yellow": (0.95, 0.82, 0.10),
    "orange": (0.96, 0.50, 0.08),
    "purple": (0.55, 0.20, 0.75),
    "cyan": (0.10, 0.75, 0.80),
    "pink": (0.95, 0.45, 0.68),
}


def episode_seed(seed: int, index: int, stream: str = "record") -> int:
    """Seed of episode ``index`` in a run seeded ``seed``; ``stream`` separates recording
    ("record") from evaluation ("eval") so evaluation never replays a training layout."""
    salt = {"record": 0, "eval": 1}[stream]
    return int(np.random.SeedSequence([int(seed), int(index), salt]).generate_state(1)[0])


@dataclass(frozen=True)
class Placement:
    """An object's initial pose on the table (world x, y in metres, yaw in radians) and colour name."""

    x: float
    y: float
    yaw: float
    color: str


@dataclass(frozen=True)
class EpisodeSpec:
    """Everything random about one episode (a pure function of ``seed``).

    Attributes:
        task: task name.
        seed: the episode seed.
        placements: initial pose and colour of every object, by object name.
        instruction: the language instruction (LeRobot's ``task`` string).
    """

    task: str
    seed: int
    placements: dict[str, Placement]
    instruction: str

    def to_dict(self) -> dict:
        return {
            "task": self.task,
            "seed": self.seed,
            "instruction": self.instruction,
            "placements": {k: vars(p) for k, p in self.placements.items()},
        }

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeSpec:
        return cls(
            d["task"],
            int(d["seed"]),
            {k: Placement(**p) for k, p in d["placements"].items()},
            d["instruction"],
        )


@dataclass(frozen=True)
class Task:
    """Move ``pick`` onto ``place``.

    Attributes:
        name: registry key.
        objects: every object in the scene (``pick``, ``place`` and distractors).
        pick, place: object names.
        pick_noun, place_noun: words used in the instruction.
        place_tolerance: how far (m) the pick's centre may lie from the place's axis.
        max_steps: step budget of an evaluation episode (control steps at 10 Hz).
    """

    name: str
    objects: tuple[ObjectSpec, ...]
    pick: str
    place: str
    pick_noun: str
    place_noun: str
    place_tolerance: float
    max_steps: int = 150

    def object(self, name: str) -> ObjectSpec:
        return next(o for o in self.objects if o.name == name)

    def sample(self, seed: int) -> EpisodeSpec:
        """Draw colours and a collision-free layout from ``seed``."""
        rng = np.random.default_rng([int(seed), 7919])
        colors = rng.choice(list(PALETTE), size=len(self.objects), replace=False)
        placed: list[tuple[float, float, float]] = []  # x, y, footprint radius
        placements = {}
        for obj, color in zip(self.objects, colors):
            radius = math.hypot(*obj.size[:2]) if obj.shape == "box" else obj.size[0]
            for _ in range(1000):
                x, y = rng.uniform(WORKSPACE_LOW, WORKSPACE_HIGH)
                if all(math.hypot(x - px, y - py) > radius + pr + 0.05 for px, py, pr in placed):
                    break
            else:
                raise RuntimeError(f"{self.name}: could not place {obj.name} (seed {seed})")
            placed.append((x, y, radius))
            placements[obj.name] = Placement(
                float(x), float(y), float(rng.uniform(-math.pi / 4, math.pi / 4)), str(color)
            )
        instruction = (
            f"put the {placements[self.pick].color} {self.pick_noun} on the "
            f"{placements[self.place].color} {self.place_noun}"
        )
        return EpisodeSpec(self.name, int(seed), placements, instruction)

    def success(self, positions: dict[str, np.ndarray], gripper_closed: bool) -> bool:
        """The pick rests on the place and the gripper has let go.

        Args:
            positions: world centre (3,) of every object.
            gripper_closed: whether the gripper is still commanded closed.
        """
        p, q = positions[self.pick], positions[self.place]
        top = q[2] + self.object(self.place).half_height + self.object(self.pick).half_height
        return (
            not gripper_closed
            and math.hypot(p[0] - q[0], p[1] - q[1]) < self.place_tolerance
            and abs(p[2] - top) < 0.01
        )


_CAN = ObjectSpec("can", "cylinder", (0.025, 0.045), 0.15)

TASKS: dict[str, Task] = {
    "pick_place": Task(
        "pick_place",
        (
            ObjectSpec("cube", "box", (0.02, 0.02, 0.02), 0.1),
            ObjectSpec("plate", "cylinder", (0.07, 0.006), 0.4),
            _CAN,
        ),
        pick="cube",
        place="plate",
        pick_noun="cube",
        place_noun="plate",
        place_tolerance=0.06,
    ),
    "stack": Task(
        "stack",
        (
            ObjectSpec("cube", "box", (0.02, 0.02, 0.02), 0.1),
            ObjectSpec("block", "box", (0.03, 0.03, 0.03), 0.4),
            _CAN,
        ),
        pick="cube",
        place="block",
        pick_noun="cube",
        place_noun="block",
        place_tolerance=0.025,
    ),
}


def get_task(task: str | Task) -> Task:
    if isinstance(task, Task):
        return task
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {sorted(TASKS)}")
    return TASKS[task]
