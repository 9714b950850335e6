"""The paper's camera perturbation protocol (GenSplat, RQ1).

A novel view is made in two steps:

1. rotate the camera about a *world* axis (X or Y) passing through the pivot by ``theta``;
2. translate it forward by ``mu`` along its own viewing axis (+z, OpenCV).

The pivot is the midpoint of the shortest segment between the optical axes of the two
external cameras (the midpoint of their centres when the axes are parallel).

Example: the named levels
    >>> list(LEVELS)
    ['none', 'small', 'medium', 'large', 'extreme', 'train']
    >>> LEVELS["large"]
    PerturbationRange(theta_deg=(18.0, 30.0), mu_m=(0.04, 0.06), random_sign=True)
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from .cameras import Cameras

AXES = ("x", "y")


@dataclass(frozen=True)
class PerturbationRange:
    """Where (theta, mu) are drawn from.

    Attributes:
        theta_deg: (low, high) rotation in degrees. With ``random_sign`` it is a magnitude
            range and the sign is drawn uniformly.
        mu_m: (low, high) forward translation in metres.
        random_sign: draw the sign of theta at random.

    Example: 5 to 10 degrees either way, up to 1 cm forward
        >>> custom = PerturbationRange(theta_deg=(5.0, 10.0), mu_m=(0.0, 0.01))
        >>> p = PerturbationSampler(custom, seed=0).sample(episode_index=0)
        >>> 5.0 <= abs(p.theta_deg) <= 10.0 and 0.0 <= p.mu_m <= 0.01
        True
    """

    theta_deg: tuple[float, float]
    mu_m: tuple[float, float]
    random_sign: bool = True

    def __post_init__(self) -> None:
        for name in ("theta_deg", "mu_m"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi)) or lo > hi:
                raise ValueError(f"PerturbationRange.{name}: need finite low <= high, got {(lo, hi)}")
        if self.random_sign and self.theta_deg[0] < 0:
            raise ValueError(
                "PerturbationRange.theta_deg: with random_sign=True it is a magnitude range and "
                f"needs low >= 0, got {self.theta_deg}"
            )


#: Named levels of the paper. "train" is the augmentation range used while training.
LEVELS: dict[str, PerturbationRange] = {
    "none": PerturbationRange((0.0, 0.0), (0.0, 0.0)),
    "small": PerturbationRange((3.0, 6.0), (0.005, 0.02)),
    "medium": PerturbationRange((8.0, 15.0), (0.02, 0.04)),
    "large": PerturbationRange((18.0, 30.0), (0.04, 0.06)),
    "extreme": PerturbationRange((60.0, 60.0), (0.12, 0.12)),
    "train": PerturbationRange((-30.0, 30.0), (0.005, 0.06), random_sign=False),
}
EVAL_LEVELS = ("none", "small", "medium", "large", "extreme")


def get_range(level: str | PerturbationRange) -> PerturbationRange:
    """Resolve a level name (see ``LEVELS``) or pass a range through."""
    if isinstance(level, PerturbationRange):
        return level
    if level not in LEVELS:
        raise ValueError(f"unknown perturbation level {level!r}; choose one of {sorted(LEVELS)}")
    return LEVELS[level]


@dataclass(frozen=True)
class Perturbation:
    """One camera move: rotation ``theta_deg`` about world ``axis`` through the pivot, then
    ``mu_m`` metres forward along the camera's viewing axis.

    Example:
        >>> p = Perturbation(axis="y", theta_deg=0.0, mu_m=0.1)
        >>> p.apply(torch.eye(4, dtype=torch.float64), pivot=torch.zeros(3))[:3, 3]  # 10 cm along +z
        tensor([0.0000, 0.0000, 0.1000], dtype=torch.float64)
    """

    axis: str = "y"
    theta_deg: float = 0.0
    mu_m: float = 0.0

    def __post_init__(self) -> None:
        if self.axis not in AXES:
            raise ValueError(f"Perturbation.axis must be one of {AXES}, got {self.axis!r}")
        if not (math.isfinite(self.theta_deg) and math.isfinite(self.mu_m)):
            raise ValueError(f"Perturbation: theta and mu must be finite, got {self.theta_deg}, {self.mu_m}")

    @property
    def is_identity(self) -> bool:
        return self.theta_deg == 0.0 and self.mu_m == 0.0

    def apply(self, c2w: torch.Tensor, pivot: torch.Tensor) -> torch.Tensor:
        """Perturbed (..., 4, 4) camera-to-world; see :func:`perturb_pose`."""
        return perturb_pose(c2w, pivot, self.axis, self.theta_deg, self.mu_m)

    def move(self, cameras: Cameras, index: int = 0) -> Cameras:
        """Camera ``index`` of a rig, moved about the pivot of the rig's cameras 0 and 1
        (the two external cameras)."""
        if not 0 <= index < len(cameras):
            raise IndexError(f"Perturbation.move: camera index {index} outside 0..{len(cameras) - 1}")
        pivot = pivot_point(cameras.c2w[0], cameras.c2w[1])
        c2w = self.apply(cameras.c2w[index : index + 1], pivot)  # a rigid motion of a checked pose
        return cameras._derive(cameras.K[index : index + 1], c2w)

    def as_dict(self) -> dict:
        return asdict(self)


def axis_rotation(axis: str, theta_deg: float, dtype=torch.float64, device=None) -> torch.Tensor:
    """(3, 3) rotation by ``theta_deg`` about the world X or Y axis (right-handed)."""
    if axis not in AXES:
        raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
    axis_angle = torch.zeros(3, dtype=dtype, device=device)
    axis_angle[AXES.index(axis)] = math.radians(theta_deg)
    return axis_angle_to_rotation_matrix(axis_angle)


def perturb_pose(
    c2w: torch.Tensor, pivot: torch.Tensor, axis: str, theta_deg: float, mu_m: float
) -> torch.Tensor:
    """Apply the protocol to (..., 4, 4) OpenCV camera-to-world poses.

    R' = R_axis R, c' = p + R_axis (c - p) + mu * R'[:, 2], with p the (3,) pivot.
    """
    Ra = axis_rotation(axis, theta_deg, c2w.dtype, c2w.device)
    p = torch.as_tensor(pivot, dtype=c2w.dtype, device=c2w.device)
    out = c2w.clone()
    R = Ra @ c2w[..., :3, :3]
    center = p + (c2w[..., :3, 3] - p) @ Ra.T
    out[..., :3, :3] = R
    out[..., :3, 3] = center + mu_m * R[..., :, 2]
    return out


def closest_points_between_axes(
    c2w_a: torch.Tensor, c2w_b: torch.Tensor, parallel_tol: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Closest points on the two optical axes (infinite lines), or None when parallel."""
    o1, d1 = c2w_a[:3, 3], c2w_a[:3, 2] / c2w_a[:3, 2].norm()
    o2, d2 = c2w_b[:3, 3], c2w_b[:3, 2] / c2w_b[:3, 2].norm()
    w = o1 - o2
    b = d1 @ d2
    denom = 1.0 - b * b  # |d1 x d2|^2 for unit directions
    if denom < parallel_tol:
        return None
    d, e = d1 @ w, d2 @ w
    s = (b * e - d) / denom
    t = (e - b * d) / denom
    return o1 + s * d1, o2 + t * d2


def pivot_point(c2w_a: torch.Tensor, c2w_b: torch.Tensor, parallel_tol: float = 1e-6) -> torch.Tensor:
    """(3,) pivot: midpoint of the shortest segment between two cameras' optical axes.

    Falls back to the midpoint of the camera centres when the axes are (near) parallel.

    Example: two cameras looking at the origin
        >>> from gensplat_transforms import look_at
        >>> pivot = pivot_point(look_at((1.0, 0.5, 0.5), (0, 0, 0)), look_at((1.0, -0.5, 0.5), (0, 0, 0)))
        >>> torch.allclose(pivot, torch.zeros(3, dtype=torch.float64))
        True
    """
    pts = closest_points_between_axes(c2w_a, c2w_b, parallel_tol)
    if pts is None:
        return 0.5 * (c2w_a[:3, 3] + c2w_b[:3, 3])
    return 0.5 * (pts[0] + pts[1])


class PerturbationSampler:
    """Seeded sampling of perturbations.

    ``mode="episode"`` (the paper's default) gives every frame of an episode the same
    perturbation, so an augmented trajectory shares one camera; ``mode="frame"`` draws a
    new one per frame. ``view`` selects one of several augmented views of the same source
    (the paper's saturation study uses about three per trajectory).

    Example:
        >>> s = PerturbationSampler("large", seed=0)
        >>> s.sample(episode_index=3) == s.sample(episode_index=3, frame_index=10)
        True
    """

    def __init__(
        self,
        level: str | PerturbationRange = "train",
        mode: str = "episode",
        seed: int = 0,
        axes: tuple[str, ...] = AXES,
    ) -> None:
        if mode not in ("episode", "frame"):
            raise ValueError(f"PerturbationSampler.mode must be 'episode' or 'frame', got {mode!r}")
        bad = [a for a in axes if a not in AXES]
        if bad or not axes:
            raise ValueError(f"PerturbationSampler.axes must be a non-empty subset of {AXES}, got {axes}")
        if int(seed) < 0:
            raise ValueError(f"PerturbationSampler.seed must be >= 0, got {seed}")
        self.range = get_range(level)
        self.mode = mode
        self.seed = int(seed)
        self.axes = tuple(axes)

    def sample(self, episode_index: int, frame_index: int = 0, view: int = 0) -> Perturbation:
        key = [self.seed, int(episode_index), int(frame_index) if self.mode == "frame" else 0, int(view)]
        if min(key) < 0:
            raise ValueError(
                f"PerturbationSampler.sample: episode/frame/view indices must be >= 0, got {key[1:]}"
            )
        rng = np.random.default_rng(key)
        axis = self.axes[int(rng.integers(len(self.axes)))]
        theta = float(rng.uniform(*self.range.theta_deg))
        if self.range.random_sign and rng.random() < 0.5:
            theta = -theta
        mu = float(rng.uniform(*self.range.mu_m))
        return Perturbation(axis=axis, theta_deg=theta + 0.0, mu_m=mu)
