"""The paper's camera perturbation protocol (GenSplat, RQ1).

A novel view is made in two steps:

1. rotate the camera about a *world* axis (X or Y) passing through the pivot by ``theta``;
2. translate it forward by ``mu`` along its own viewing axis (+z, OpenCV).

The pivot is the midpoint of the shortest segment between the optical axes of the two
external cameras (the midpoint of their centres when the axes are parallel). A rig with one
external camera has its pivot on that camera's optical axis, at the median depth of the scene
it sees (``pivot_depth``; ``gensplat cache`` measures it on the cached timesteps): where a
second camera looking at the same scene would put it.

Example: the named levels
    >>> list(LEVELS)
    ['none', 'small', 'medium', 'large', 'extreme', 'train']
    >>> LEVELS["large"]
    PerturbationRange(theta_deg=(18.0, 30.0), mu_m=(0.04, 0.06), random_sign=True)
"""

from __future__ import annotations

import math
from collections.abc import Sequence
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

    def move(self, cameras: Cameras, index: int = 0, pivot_depth: float | None = None) -> Cameras:
        """Camera ``index`` of a rig, moved about the rig's pivot (:func:`rig_pivot`: of its
        cameras 0 and 1, or ``pivot_depth`` along the axis of a rig's one camera)."""
        if not 0 <= index < len(cameras):
            raise IndexError(f"Perturbation.move: camera index {index} outside 0..{len(cameras) - 1}")
        move = torch.tensor([self.as_row()], dtype=cameras.c2w.dtype)
        c2w = move_rig(cameras.c2w, move, [index], pivot_depth)  # a rigid motion of a checked pose
        return cameras._derive(cameras.K[index : index + 1], c2w)

    def as_row(self) -> list[float]:
        """The move as (axis index into ``AXES``, theta_deg, mu_m): one row of the moves that
        :func:`move_rig` takes."""
        return [AXES.index(self.axis), self.theta_deg, self.mu_m]

    def as_dict(self) -> dict:
        return asdict(self)


def axis_rotation(axis: str | torch.Tensor, theta_deg: float | torch.Tensor, dtype=torch.float64,
                  device=None) -> torch.Tensor:
    """(..., 3, 3) rotations by ``theta_deg`` (degrees, float or (...)) about the world X or Y
    axis (right-handed); ``axis`` is "x" or "y", or (...) indices into ``AXES``. Kornia's
    axis-angle formula, element by element (a batch gives each element's own bits)."""
    if isinstance(axis, str):
        if axis not in AXES:
            raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
        axis = torch.tensor(AXES.index(axis), device=device)
    elif not bool(((axis == 0) | (axis == 1)).all()):
        raise ValueError(f"axis indices must be 0 (x) or 1 (y), got {axis.unique().tolist()}")
    theta = (torch.as_tensor(theta_deg, dtype=torch.float64, device=device) * (math.pi / 180)).to(dtype)
    theta, axis = torch.broadcast_tensors(theta, axis.to(device=theta.device))
    axis_angle = torch.zeros(*theta.shape, 3, dtype=dtype, device=theta.device)
    axis_angle.scatter_(-1, axis[..., None].long(), theta[..., None])
    return axis_angle_to_rotation_matrix(axis_angle.reshape(-1, 3)).reshape(*theta.shape, 3, 3)


def perturb_pose(c2w: torch.Tensor, pivot: torch.Tensor, axis: str | torch.Tensor, theta_deg: float | torch.Tensor,
                 mu_m: float | torch.Tensor) -> torch.Tensor:
    """Apply the protocol to (..., 4, 4) OpenCV camera-to-world poses.

    R' = R_axis R, c' = p + R_axis (c - p) + mu * R'[:, 2], with p the pivot ((3,) or
    (..., 3)); ``axis``, ``theta_deg`` and ``mu_m`` are one move or (...) moves, one per pose
    (see :func:`axis_rotation`).
    """
    Ra = axis_rotation(axis, theta_deg, c2w.dtype, c2w.device)
    p = torch.as_tensor(pivot, dtype=c2w.dtype, device=c2w.device)
    mu = torch.as_tensor(mu_m, dtype=c2w.dtype, device=c2w.device)
    out = c2w.clone()
    R = Ra @ c2w[..., :3, :3]
    center = p + (Ra @ (c2w[..., :3, 3] - p)[..., None])[..., 0]
    out[..., :3, :3] = R
    out[..., :3, 3] = center + mu[..., None] * R[..., :, 2]
    return out


def move_rig(c2w: torch.Tensor, moves: torch.Tensor, views: Sequence[int], pivot_depth: float | None = None
             ) -> torch.Tensor:  # fmt: skip
    """(..., R, 4, 4) poses of the cameras ``views`` (R indices) of rigs of (..., V, 4, 4)
    camera-to-world poses, each moved about its rig's pivot (:func:`rig_pivot`) by its move of
    the (..., R, 3) ``moves`` (axis index into ``AXES``, theta_deg, mu_m): what
    :meth:`Perturbation.move` does to one camera, for any batch of rigs (the batch path moves a
    whole training batch's cameras with it).

    Example: the left camera of a rig turned 5 deg about world X
        >>> from gensplat_transforms import look_at
        >>> rig = torch.stack([look_at((1.0, 0.3, 0.5), (0, 0, 0)), look_at((1.0, -0.3, 0.5), (0, 0, 0))])
        >>> move_rig(rig, torch.tensor([[0, 5.0, 0.0]], dtype=torch.float64), [0]).shape
        torch.Size([1, 4, 4])
    """
    pivot = rig_pivot(c2w, pivot_depth)[..., None, :]  # (..., 1, 3)
    axis, theta, mu = moves.unbind(-1)
    return perturb_pose(c2w[..., list(views), :, :], pivot, axis.long(), theta, mu)


def _closest(c2w_a: torch.Tensor, c2w_b: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Closest points (..., 3) on the optical axes of (..., 4, 4) poses, and |d1 x d2|^2 (...)
    (the points are not finite where it is 0: parallel axes)."""
    o1, d1 = c2w_a[..., :3, 3], c2w_a[..., :3, 2] / c2w_a[..., :3, 2].norm(dim=-1, keepdim=True)
    o2, d2 = c2w_b[..., :3, 3], c2w_b[..., :3, 2] / c2w_b[..., :3, 2].norm(dim=-1, keepdim=True)
    w = o1 - o2
    b = (d1 * d2).sum(-1)
    denom = 1.0 - b * b  # |d1 x d2|^2 for unit directions
    d, e = (d1 * w).sum(-1), (d2 * w).sum(-1)
    s = (b * e - d) / denom
    t = (e - b * d) / denom
    return o1 + s[..., None] * d1, o2 + t[..., None] * d2, denom


def closest_points_between_axes(
    c2w_a: torch.Tensor, c2w_b: torch.Tensor, parallel_tol: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Closest points on the two optical axes (infinite lines), or None when parallel."""
    pa, pb, denom = _closest(c2w_a, c2w_b)
    return None if denom < parallel_tol else (pa, pb)


def rig_pivot(c2w: torch.Tensor, pivot_depth: float | None = None) -> torch.Tensor:
    """(..., 3) pivot of rigs of (..., V, 4, 4) camera poses: :func:`pivot_point` of cameras 0
    and 1, or with one camera (V = 1) the point ``pivot_depth`` metres along its optical axis.

    Example: one camera at the origin looking along +z
        >>> rig_pivot(torch.eye(4, dtype=torch.float64)[None], pivot_depth=0.8)
        tensor([0.0000, 0.0000, 0.8000], dtype=torch.float64)
    """
    if c2w.shape[-3] > 1:
        return pivot_point(c2w[..., 0, :, :], c2w[..., 1, :, :])
    if pivot_depth is None or not (math.isfinite(pivot_depth) and pivot_depth > 0):
        raise ValueError(f"a rig of one external camera needs a positive pivot_depth (metres along its optical "
                         f"axis), got {pivot_depth}")  # fmt: skip
    axis = c2w[..., 0, :3, 2]
    return c2w[..., 0, :3, 3] + pivot_depth * axis / axis.norm(dim=-1, keepdim=True)


def pivot_point(c2w_a: torch.Tensor, c2w_b: torch.Tensor, parallel_tol: float = 1e-6) -> torch.Tensor:
    """(..., 3) pivot of (..., 4, 4) camera pairs: midpoint of the shortest segment between
    two cameras' optical axes.

    Falls back to the midpoint of the camera centres when the axes are (near) parallel.

    Example: two cameras looking at the origin
        >>> from gensplat_transforms import look_at
        >>> pivot = pivot_point(look_at((1.0, 0.5, 0.5), (0, 0, 0)), look_at((1.0, -0.5, 0.5), (0, 0, 0)))
        >>> torch.allclose(pivot, torch.zeros(3, dtype=torch.float64))
        True
    """
    pa, pb, denom = _closest(c2w_a, c2w_b)
    parallel = (denom < parallel_tol)[..., None]
    return torch.where(parallel, 0.5 * (c2w_a[..., :3, 3] + c2w_b[..., :3, 3]), 0.5 * (pa + pb))


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
