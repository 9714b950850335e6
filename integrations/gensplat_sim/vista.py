"""VISTA's evaluation camera samplers, a second evaluation protocol beside the paper's.

Written from the published description of VISTA's ``camera_pose_sampler.py`` (github
s-tian/VISTA), not from its code:

* ``small_perturb``: the camera's centre moves by Gaussian noise of standard deviation 3 cm
  per world axis, and its orientation turns about a uniformly random axis by a Gaussian
  angle of standard deviation 0.075 rad;
* ``arc_90deg``: the camera moves on an arc of +-45 deg azimuth (uniform) about the vertical
  axis through the scene centre (the point the camera looks at), keeping its elevation, at
  its distance from the centre plus Gaussian noise of standard deviation 5 cm, and looks at
  the centre with the image's up towards world +z.

Poses are OpenCV camera-to-world (4, 4) float64 tensors (x right, y down, z forward) in a
world whose +z is up; the centre is a (3,) tensor. A move is drawn once per episode,
reproducibly from (seed, episode index), as ``PaperSampler`` draws the paper's levels.

Example:
    >>> from gensplat_transforms.core.cameras import look_at
    >>> nominal, centre = look_at((1.0, 0.4, 0.5), (0.45, 0.0, 0.12)), torch.tensor([0.45, 0.0, 0.12])
    >>> move = VistaSampler("arc_90deg", seed=0).sample(episode_index=3)
    >>> moved = move.apply(nominal, centre)
    >>> abs(move.azimuth_deg) <= 45.0, moved.shape
    (True, torch.Size([4, 4]))
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from gensplat_transforms.core.cameras import look_at

#: The samplers, in the order that salts their seeds.
SAMPLERS = ("small_perturb", "arc_90deg")
POSITION_STD_M = 0.03
ANGLE_STD_RAD = 0.075
ARC_HALF_ANGLE_DEG = 45.0
RADIUS_STD_M = 0.05
UP = (0.0, 0.0, 1.0)


def rotation(axis_angle: torch.Tensor) -> torch.Tensor:
    """(3, 3) rotation by ``|axis_angle|`` radians about the (3,) ``axis_angle``'s direction."""
    return axis_angle_to_rotation_matrix(axis_angle[None])[0]


@dataclass(frozen=True)
class SmallPerturb:
    """``small_perturb``: the centre moves by ``offset_m`` (world, metres) and the orientation
    turns by ``angle_rad`` about the unit world axis ``rotation_axis``."""

    offset_m: tuple[float, float, float]
    rotation_axis: tuple[float, float, float]
    angle_rad: float

    def apply(self, c2w: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """The moved (4, 4) camera-to-world of a (4, 4) one; ``centre`` is unused (every
        move takes the scene centre)."""
        out = c2w.clone()
        out[:3, :3] = (
            rotation(torch.tensor(self.rotation_axis, dtype=c2w.dtype) * self.angle_rad) @ c2w[:3, :3]
        )
        out[:3, 3] = c2w[:3, 3] + torch.tensor(self.offset_m, dtype=c2w.dtype)
        return out

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class ArcMove:
    """``arc_90deg``: the camera turns by ``azimuth_deg`` about the vertical axis through the
    centre, its distance to the centre grows by ``radius_noise_m``, and it looks at the centre."""

    azimuth_deg: float
    radius_noise_m: float

    def apply(self, c2w: torch.Tensor, centre: torch.Tensor) -> torch.Tensor:
        """The moved (4, 4) camera-to-world of a (4, 4) one about the (3,) ``centre``.
        Raises ValueError when the noisy distance is not positive."""
        centre = torch.as_tensor(centre, dtype=c2w.dtype)
        offset = c2w[:3, 3] - centre
        radius = float(offset.norm()) + self.radius_noise_m
        if radius <= 0:
            raise ValueError(
                f"ArcMove: distance {float(offset.norm()):.3f} m + noise {self.radius_noise_m:.3f} m <= 0"
            )
        turn = rotation(torch.tensor([0.0, 0.0, math.radians(self.azimuth_deg)], dtype=c2w.dtype))
        eye = centre + turn @ offset * (radius / offset.norm())
        return look_at(eye, centre, UP, dtype=c2w.dtype)

    def as_dict(self) -> dict:
        return asdict(self)


class VistaSampler:
    """Seeded draws of one VISTA sampler: ``sample(i)`` is the move of episode ``i``.

    Args:
        name: ``small_perturb`` or ``arc_90deg``.
        seed: with the episode index, seeds the draw (numpy's ``default_rng([seed, episode,
            sampler index])``).
    """

    def __init__(self, name: str, seed: int = 0) -> None:
        if name not in SAMPLERS:
            raise ValueError(f"unknown VISTA sampler {name!r}; choose one of {SAMPLERS}")
        if int(seed) < 0:
            raise ValueError(f"VistaSampler.seed must be >= 0, got {seed}")
        self.name, self.seed = name, int(seed)

    def sample(self, episode_index: int) -> SmallPerturb | ArcMove:
        if episode_index < 0:
            raise ValueError(f"VistaSampler.sample: episode index must be >= 0, got {episode_index}")
        rng = np.random.default_rng([self.seed, int(episode_index), SAMPLERS.index(self.name)])
        if self.name == "small_perturb":
            axis = rng.normal(size=3)  # a normalised isotropic Gaussian: uniform on the sphere
            offset = rng.normal(0.0, POSITION_STD_M, 3)
            angle = float(rng.normal(0.0, ANGLE_STD_RAD))
            return SmallPerturb(tuple(offset.tolist()), tuple((axis / np.linalg.norm(axis)).tolist()), angle)
        azimuth = float(rng.uniform(-ARC_HALF_ANGLE_DEG, ARC_HALF_ANGLE_DEG))
        return ArcMove(azimuth, float(rng.normal(0.0, RADIUS_STD_M)))
