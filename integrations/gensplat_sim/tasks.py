"""Tabletop tasks: which objects a scene holds, how an episode is randomised, the instruction
string and success detection.

The tasks (all but ``reach_solo`` with distractors on the table):

* ``pick_place``: move a 4 cm cube onto a plate;
* ``stack``: move a 4 cm cube onto a 6 cm cube;
* ``reach``: bring the open gripper to just above a 4 cm cube (no ``place`` object). The
  shortest closed-loop task in which the policy must find an object in the image
  (demonstrations of 15-18 steps), meant for small training budgets;
* ``reach_solo``: the same with a single 5 cm cube in a colour that stands out from the
  wooden table and no distractors: the policy only has to find the one object in view. This is
  the task a from-scratch image encoder learns on a CPU budget;
* ``reach_marked``: two 5 cm cubes placed at random, the one to reach always red, the other
  in another contrasting colour: the policy must tell which cube is marked from the image, so
  its success depends on what the external camera shows.

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
    ("record") from evaluation ("eval") so evaluation never replays a training layout, and
    both from the policy's sampling noise in an evaluation ("policy")."""
    salt = {"record": 0, "eval": 1, "policy": 2}[stream]
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
    """Move ``pick`` onto ``place``, or, when ``place`` is None, reach ``pick``: bring the
    pinch point to :data:`REACH_CLEARANCE` above its top.

    Attributes:
        name: registry key.
        objects: every object in the scene (``pick``, ``place`` and distractors).
        pick, place: object names (``place`` None: a reach task).
        pick_noun, place_noun: words used in the instruction.
        place_tolerance: how far (m) the pick's centre may lie from the place's axis; for a
            reach, how far the pinch point may lie from its goal.
        max_steps: step budget of an evaluation episode (control steps at 10 Hz).
        colors: the palette names objects are coloured from (default all of :data:`PALETTE`).
        pick_color: the colour the ``pick`` object always has (the others never), or None
            (drawn like the others).
    """

    name: str
    objects: tuple[ObjectSpec, ...]
    pick: str
    place: str | None
    pick_noun: str
    place_noun: str
    place_tolerance: float
    max_steps: int = 150
    colors: tuple[str, ...] = tuple(PALETTE)
    pick_color: str | None = None

    def object(self, name: str) -> ObjectSpec:
        return next(o for o in self.objects if o.name == name)

    def sample(self, seed: int) -> EpisodeSpec:
        """Draw colours and a collision-free layout from ``seed``."""
        rng = np.random.default_rng([int(seed), 7919])
        if self.pick_color is None:
            colors = rng.choice(list(self.colors), size=len(self.objects), replace=False)
        else:
            others = iter(rng.choice([c for c in self.colors if c != self.pick_color], size=len(self.objects) - 1,
                                     replace=False))  # fmt: skip
            colors = [self.pick_color if o.name == self.pick else next(others) for o in self.objects]
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
        pick = f"{placements[self.pick].color} {self.pick_noun}"
        if self.place is None:
            instruction = f"reach the {pick}"
        else:
            instruction = f"put the {pick} on the {placements[self.place].color} {self.place_noun}"
        return EpisodeSpec(self.name, int(seed), placements, instruction)

    def reach_goal(self, pick_position: np.ndarray) -> np.ndarray:
        """Pinch-point goal (3,) of a reach: :data:`REACH_CLEARANCE` above the pick's top."""
        return pick_position + (0.0, 0.0, self.object(self.pick).half_height + REACH_CLEARANCE)

    def success(self, positions: dict[str, np.ndarray], gripper_closed: bool, pinch: np.ndarray) -> bool:
        """Pick and place: the pick rests on the place and the gripper has let go. Reach: the
        pinch point is within ``place_tolerance`` of :meth:`reach_goal` with the gripper open.

        Args:
            positions: world centre (3,) of every object.
            gripper_closed: whether the gripper is commanded closed.
            pinch: world position (3,) of the gripper's pinch point.
        """
        if self.place is None:
            error = np.linalg.norm(pinch - self.reach_goal(positions[self.pick]))
            return not gripper_closed and bool(error < self.place_tolerance)
        p, q = positions[self.pick], positions[self.place]
        top = q[2] + self.object(self.place).half_height + self.object(self.pick).half_height
        return (
            not gripper_closed
            and math.hypot(p[0] - q[0], p[1] - q[1]) < self.place_tolerance
            and abs(p[2] - top) < 0.01
        )


#: Height (m) of a reach's pinch-point goal above the top of the pick object.
REACH_CLEARANCE = 0.02

_CUBE = ObjectSpec("cube", "box", (0.02, 0.02, 0.02), 0.1)
_PLATE = ObjectSpec("plate", "cylinder", (0.07, 0.006), 0.4)
_CAN = ObjectSpec("can", "cylinder", (0.025, 0.045), 0.15)
#: Palette colours with high contrast to the wooden table (no yellow, orange or pink).
_CONTRAST = ("red", "green", "blue", "purple", "cyan")


def _reach(name: str, objects: tuple[ObjectSpec, ...], **options) -> Task:
    """A reach of the object named "cube" among ``objects``: within 2.5 cm, in 50 steps."""
    return Task(name, objects, pick="cube", place=None, pick_noun="cube", place_noun="",
                place_tolerance=0.025, max_steps=50, **options)  # fmt: skip


TASKS: dict[str, Task] = {
    "pick_place": Task(
        "pick_place",
        (_CUBE, _PLATE, _CAN),
        pick="cube",
        place="plate",
        pick_noun="cube",
        place_noun="plate",
        place_tolerance=0.06,
    ),
    "stack": Task(
        "stack",
        (_CUBE, ObjectSpec("block", "box", (0.03, 0.03, 0.03), 0.4), _CAN),
        pick="cube",
        place="block",
        pick_noun="cube",
        place_noun="block",
        place_tolerance=0.025,
    ),
    "reach": _reach("reach", (_CUBE, _PLATE, _CAN)),
    "reach_solo": _reach(
        "reach_solo", (ObjectSpec("cube", "box", (0.025, 0.025, 0.025), 0.1),), colors=_CONTRAST
    ),
    "reach_marked": _reach(
        "reach_marked",
        (ObjectSpec("cube", "box", (0.025, 0.025, 0.025), 0.1), ObjectSpec("decoy", "box", (0.025, 0.025, 0.025), 0.1)),
        colors=_CONTRAST,
        pick_color="red",
    ),
}


def get_task(task: str | Task) -> Task:
    if isinstance(task, Task):
        return task
    if task not in TASKS:
        raise ValueError(f"unknown task {task!r}; choose one of {sorted(TASKS)}")
    return TASKS[task]
