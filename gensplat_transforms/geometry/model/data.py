"""Training samples for the GenSplat model: the external cameras of one timestep as :class:`Views`.

:class:`ProceduralViews` draws endless procedural tabletops (``TabletopScene``) seen by random
DROID-like camera rigs, with exact RGB-D and calibration; ``gensplat_lerobot.LeRobotViews``
reads the external cameras of a local LeRobot dataset. Both return images whose size is a
multiple of the patch size, ready for the model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch.utils.data import Dataset

from ...core.cameras import Cameras, focal_from_fov, look_at
from ...core.views import Views
from ...data.scenes import WORKSPACE_CENTER, TabletopScene
from .config import PATCH_SIZE


@dataclass(frozen=True)
class RigConfig:
    """Random external-camera rigs around the workspace (angles in degrees, lengths in metres).

    Cameras stand on the far side of the table from the robot (which is at -x), as in DROID:
    each at its own azimuth about world z (0 = +x), at least ``min_separation`` apart. The
    default cameras of :func:`~gensplat_transforms.data.scenes.default_cameras` (azimuths 64 and
    -59 deg, 0.83 m away, 34 deg up, 60 deg field of view) lie inside these ranges.

    Attributes:
        azimuth: range of every camera's azimuth.
        min_separation: smallest azimuth difference between two cameras of a rig.
        distance: eye distance from the look-at point.
        elevation: eye elevation above the look-at point's horizontal plane.
        target_jitter: half width of the box around ``WORKSPACE_CENTER`` the cameras look at.
        fov: vertical field of view (the same for all cameras of a rig).
    """

    azimuth: tuple[float, float] = (-100.0, 100.0)
    min_separation: float = 30.0
    distance: tuple[float, float] = (0.65, 1.05)
    elevation: tuple[float, float] = (20.0, 55.0)
    target_jitter: float = 0.1
    fov: tuple[float, float] = (50.0, 70.0)

    def sample(self, rng: np.random.Generator, num_views: int, size: int) -> Cameras:
        """``num_views`` cameras of ``size x size`` pixels, float64."""
        while True:  # rejection sampling of well separated azimuths
            az = rng.uniform(*self.azimuth, num_views)
            if num_views == 1 or np.diff(np.sort(az)).min() >= self.min_separation:
                break
        c2w = []
        for a in np.radians(az):
            target = np.asarray(WORKSPACE_CENTER) + rng.uniform(-self.target_jitter, self.target_jitter, 3)
            r, el = rng.uniform(*self.distance), math.radians(rng.uniform(*self.elevation))
            eye = target + r * np.array(
                [math.cos(a) * math.cos(el), math.sin(a) * math.cos(el), math.sin(el)]
            )
            c2w.append(look_at(eye.tolist(), target.tolist()))
        f = focal_from_fov(rng.uniform(*self.fov), size)
        return Cameras.from_intrinsics(f, f, size / 2, size / 2, torch.stack(c2w), size, size)


class ProceduralViews(Dataset):
    """Sample i: ``TabletopScene(seed + i)`` seen by a random rig, rendered exactly.

    Deterministic in (seed, i), so a resumed run sees the same data. Items are :class:`Views`
    with images (V, 3, S, S), calibrated cameras and metric depth (V, 1, S, S).

    Args:
        length: number of samples (scenes); any index below it is a new scene.
        size: image side in pixels, a multiple of 14.
        num_views: cameras per sample.
        seed: first scene seed; held-out evaluation uses seeds beyond ``seed + length``.
        rig: camera sampling ranges.
    """

    def __init__(self, length: int, size: int = 112, num_views: int = 2, seed: int = 0,
                 rig: RigConfig = RigConfig()) -> None:  # fmt: skip
        if size % PATCH_SIZE:
            raise ValueError(f"ProceduralViews: size must be a multiple of {PATCH_SIZE}, got {size}")
        if num_views < 1 or length < 1:
            raise ValueError(f"ProceduralViews: need length, num_views >= 1, got {length}, {num_views}")
        self.length, self.size, self.num_views, self.seed, self.rig = length, size, num_views, seed, rig

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, i: int) -> Views:
        if not 0 <= i < self.length:
            raise IndexError(f"ProceduralViews: index {i} out of range for {self.length} samples")
        cameras = self.rig.sample(np.random.default_rng([self.seed, i]), self.num_views, self.size)
        rgb, depth = TabletopScene(self.seed + i).render(cameras)
        return Views(rgb, cameras, depth)

