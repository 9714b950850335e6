"""Camera perturbations: the paper's protocol (GenSplat, RQ1) and wider samplers.

A novel view is made in up to four steps (:class:`Perturbation`):

1. rotate the camera about a *world* axis passing through the pivot by ``theta`` (the
   paper: world X or Y), or through the camera's own centre (``about="camera"``: its
   orientation turned, as a bumped mount is);
2. shift it by ``shift_m`` in the world (position noise; the paper: none);
3. translate it forward by ``mu`` along its own viewing axis (+z, OpenCV);
4. scale its focal length by ``focal_scale``, the principal point and image size kept (a
   zoom or another lens; the paper: none).

The samplers draw these per episode (or frame) and view, seeded: :class:`PaperSampler`
the paper's levels (rotation about X or Y, forward step), :class:`TiltSampler` turns of the
camera about a uniformly random axis through its own centre with a position shift, :class:`ArcSampler` turns about the world's
vertical (+z up) through the pivot, as a camera moved along an arc around the scene,
:class:`MixSampler` one of them per move; each can add a focal-length change.

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
import operator
import sys
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from ..core.cameras import Cameras, _check_rigid, _closest, pivot_point, rigid_tolerance
from ..core.renamed import renamed

#: world axes a move can turn about by name; the paper's levels use x and y (``PAPER_AXES``)
AXES = ("x", "y", "z")
PAPER_AXES = ("x", "y")
#: the kinds of move a sampler draws
KINDS = ("paper", "tilt", "arc")
#: the samplers :func:`make_sampler` makes by name ("mix": one of :data:`KINDS` per move); it
#: also takes several kinds separated by commas (one of them per move, e.g. "tilt,arc")
SAMPLERS = (*KINDS, "mix")
#: width of a move's row (:meth:`Perturbation.as_row`): axis (3), theta_deg, mu_m, shift_m (3), focal_scale,
#: pivot share (1: the rotation is about the pivot, 0: about the camera's centre)
ROW = 10
#: where a move's rotation turns the camera about (:attr:`Perturbation.about`)
ABOUT = ("pivot", "camera")
#: the focal-length factors a move may have (a 1000x zoom either way): beyond them a float32
#: projection overflows and a render comes back empty, which no lens calls for
FOCAL_SCALE_LIMITS = (1e-3, 1e3)


@dataclass(frozen=True)
class Moves:
    """Camera moves of any batch shape (...), by name: what rows of :data:`ROW` floats
    (:meth:`Perturbation.as_row`; the form items and batches carry, ``plan.BATCH_KEYS``) hold.

    Attributes:
        axis: (..., 3) unit rotation axis (world); theta_deg, mu_m: (...) the rotation and the
            step forward; shift_m: (..., 3) the world shift; focal_scale: (...) the focal-length
            factor; pivot: (...) 1 where the rotation turns about the rig's pivot, 0 about the
            camera's own centre.

    Example:
        >>> m = Moves.of_rows(torch.tensor([Perturbation("x", 5.0, 0.02).as_row()]))
        >>> m.theta_deg, m.axis
        (tensor([5.], dtype=torch.float64), tensor([[1., 0., 0.]], dtype=torch.float64))
    """

    axis: torch.Tensor
    theta_deg: torch.Tensor
    mu_m: torch.Tensor
    shift_m: torch.Tensor
    focal_scale: torch.Tensor
    pivot: torch.Tensor

    @classmethod
    def of_rows(cls, rows: torch.Tensor) -> Moves:
        """The moves of (..., :data:`ROW`) rows, in float64."""
        if not isinstance(rows, torch.Tensor) or rows.ndim < 1 or rows.shape[-1] != ROW:
            shape = tuple(rows.shape) if isinstance(rows, torch.Tensor) else type(rows).__name__
            raise ValueError(f"Moves: need (..., {ROW}) rows (Perturbation.as_row), got {shape}")
        r = rows.to(torch.float64)
        return cls(r[..., 0:3], r[..., 3], r[..., 4], r[..., 5:8], r[..., 8], r[..., 9])


def _real(name: str, value) -> float:
    """``value`` as a float, or ``TypeError`` naming ``name`` unless it is a number (a bool or a
    string is not)."""
    if not isinstance(value, (bool, str, bytes)):
        try:
            return float(value)
        except (TypeError, ValueError):
            pass
    raise TypeError(f"{name} must be a number, got {value!r}")


def _integer(name: str, value) -> int:
    """``value`` as an int, or ``TypeError`` naming ``name`` unless it is an integer (Python,
    NumPy or torch) or a float without a fractional part."""
    if not isinstance(value, (bool, str, bytes)):
        try:
            return operator.index(value)
        except TypeError:
            if isinstance(value, float) and value.is_integer():
                return int(value)
    raise TypeError(f"{name} must be an integer, got {value!r}")


def _numbers(name: str, value, n: int, what: str = "") -> Sequence:
    """``value``, or ``TypeError`` naming ``name`` (and ``what`` it must be) unless it is a
    sequence of ``n`` items (not a string)."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != n:
        raise TypeError(f"{name} must be {what or f'{n} numbers'}, got {value!r}")
    return value


def _pair(name: str, value) -> tuple[float, float]:
    """``value`` as (low, high) floats, or ``TypeError`` naming ``name`` unless it is two numbers."""
    lo, hi = _numbers(name, value, 2, "(low, high), two numbers")
    return _real(name, lo), _real(name, hi)


def _focal_range(name: str, value) -> tuple[float, float]:
    """``value`` as (low, high) floats, or an error naming ``name`` unless 0 < low <= high and
    both lie in :data:`FOCAL_SCALE_LIMITS`."""
    lo, hi = _pair(name, value)
    if not 0 < lo <= hi < math.inf:
        raise ValueError(f"{name}: need 0 < low <= high, got {(lo, hi)}")
    if not FOCAL_SCALE_LIMITS[0] <= lo <= hi <= FOCAL_SCALE_LIMITS[1]:
        raise ValueError(f"{name}: {(lo, hi)} reaches outside the focal-length factors "
                         f"{FOCAL_SCALE_LIMITS[0]:g} to {FOCAL_SCALE_LIMITS[1]:g} a render can show")  # fmt: skip
    return lo, hi


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
        >>> p = PaperSampler(custom, seed=0).sample(episode_index=0)
        >>> 5.0 <= abs(p.theta_deg) <= 10.0 and 0.0 <= p.mu_m <= 0.01
        True
    """

    theta_deg: tuple[float, float]
    mu_m: tuple[float, float]
    random_sign: bool = True

    def __post_init__(self) -> None:
        for name in ("theta_deg", "mu_m"):
            lo, hi = _pair(f"PerturbationRange.{name}", getattr(self, name))
            if not math.isfinite(hi - lo) or lo > hi:  # a finite width: one to draw from
                raise ValueError(f"PerturbationRange.{name}: need finite low <= high, a finite width apart, got "
                                 f"{(lo, hi)}")  # fmt: skip
            object.__setattr__(self, name, (lo, hi))
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
    """One camera move: rotation ``theta_deg`` about the world ``axis`` through the pivot (or,
    with ``about="camera"``, through the camera's own centre), a world shift ``shift_m``, then
    ``mu_m`` metres forward along the camera's viewing axis; its focal length scaled by
    ``focal_scale`` (principal point and image size kept).

    ``axis`` is "x", "y" or "z", or a (3,) direction (stored normalised).

    Example:
        >>> p = Perturbation(axis="y", theta_deg=0.0, mu_m=0.1)
        >>> p.apply(torch.eye(4, dtype=torch.float64), pivot=torch.zeros(3))[:3, 3]  # 10 cm along +z
        tensor([0.0000, 0.0000, 0.1000], dtype=torch.float64)
    """

    axis: str | tuple[float, float, float] = "y"
    theta_deg: float = 0.0
    mu_m: float = 0.0
    shift_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    focal_scale: float = 1.0
    about: str = "pivot"

    def __post_init__(self) -> None:
        if self.about not in ABOUT:
            raise ValueError(f"Perturbation.about must be one of {ABOUT}, got {self.about!r}")
        if isinstance(self.axis, str):
            if self.axis not in AXES:
                raise ValueError(f"Perturbation.axis must be one of {AXES} or a direction (x, y, z), got {self.axis!r}")
        else:
            v = tuple(_real("Perturbation.axis", a) for a in _numbers("Perturbation.axis", self.axis, 3))
            norm = math.hypot(*v)  # no overflow or underflow of the squares
            if not (math.isfinite(norm) and norm > 0):
                raise ValueError(f"Perturbation.axis: a direction needs 3 finite values, not all 0, got {self.axis}")
            # a unit direction is kept as it is: normalising it again could change its last bits
            object.__setattr__(self, "axis", v if abs(norm - 1.0) <= 1e-15 else tuple(a / norm for a in v))
        shift = tuple(_real("Perturbation.shift_m", a) for a in _numbers("Perturbation.shift_m", self.shift_m, 3))
        if not all(math.isfinite(a) for a in shift):
            raise ValueError(f"Perturbation.shift_m must be 3 finite metres, got {self.shift_m}")
        object.__setattr__(self, "shift_m", shift)
        for name in ("theta_deg", "mu_m", "focal_scale"):
            object.__setattr__(self, name, _real(f"Perturbation.{name}", getattr(self, name)))
        if not (math.isfinite(self.theta_deg) and math.isfinite(self.mu_m)):
            raise ValueError(f"Perturbation: theta and mu must be finite, got {self.theta_deg}, {self.mu_m}")
        lo, hi = FOCAL_SCALE_LIMITS
        if not lo <= self.focal_scale <= hi:
            raise ValueError(f"Perturbation.focal_scale must be a factor from {lo:g} to {hi:g}, got {self.focal_scale}")

    @property
    def is_identity(self) -> bool:
        return self.theta_deg == 0.0 and self.mu_m == 0.0 and self.shift_m == (0.0,) * 3 and self.focal_scale == 1.0

    @property
    def direction(self) -> tuple[float, float, float]:
        """The rotation axis as a unit (3,) world direction."""
        if not isinstance(self.axis, str):
            return self.axis
        i = AXES.index(self.axis)
        return tuple(float(k == i) for k in range(3))

    def apply(self, c2w: torch.Tensor, pivot: torch.Tensor) -> torch.Tensor:
        """Moved (..., 4, 4) camera-to-world (the focal length aside); see :func:`perturb_pose`,
        which checks the result."""
        return perturb_pose(c2w, pivot, torch.tensor(self.direction, dtype=torch.float64), self.theta_deg, self.mu_m,
                            torch.tensor(self.shift_m, dtype=torch.float64), float(self.about == "pivot"))  # fmt: skip

    def move(self, cameras: Cameras, index: int = 0, pivot_depth: float | None = None) -> Cameras:
        """Camera ``index`` of a rig, moved about the rig's pivot (:func:`rig_pivot`: of its
        cameras 0 and 1, or ``pivot_depth`` along the axis of a rig's one camera; a move about
        the camera's own centre needs no pivot), its focal length scaled (:func:`scale_focal`).
        The move is taken in float64 (as the batch path's rows), whatever the cameras' dtype."""
        if not 0 <= index < len(cameras):
            raise IndexError(f"Perturbation.move: camera index {index} outside 0..{len(cameras) - 1}")
        move = Moves.of_rows(torch.tensor([self.as_row()], dtype=torch.float64))
        c2w = _move_rig(cameras.c2w, move, [index], pivot_depth)  # a rigid motion of a checked pose
        return cameras._derive(scale_focal(cameras.K[index : index + 1], move.focal_scale), c2w)

    def as_row(self) -> list[float]:
        """The move as one row of :data:`ROW` floats: axis direction (3), theta_deg, mu_m,
        shift_m (3), focal_scale, pivot share (what :func:`move_rig` and :func:`scale_focal` take)."""
        return [*self.direction, self.theta_deg, self.mu_m, *self.shift_m, self.focal_scale,
                float(self.about == "pivot")]  # fmt: skip

    def as_dict(self) -> dict:
        """The move's fields; a shift and focal scale only where the move has them (a paper
        move reads as (axis, theta_deg, mu_m))."""
        d = asdict(self)
        if self.shift_m == (0.0, 0.0, 0.0):
            del d["shift_m"]
        if self.focal_scale == 1.0:
            del d["focal_scale"]
        if self.about == "pivot":
            del d["about"]
        return d


def scale_focal(K: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) intrinsics with their focal lengths (and skew) multiplied by (...) ``scale``,
    the principal point kept; ValueError where a factor lies outside :data:`FOCAL_SCALE_LIMITS`
    or a focal length so scaled is not a finite positive number of K's dtype."""
    lo, hi = FOCAL_SCALE_LIMITS
    outside = ~((scale >= lo) & (scale <= hi))  # NaN included
    if outside.any():
        raise ValueError(f"scale_focal: focal_scale {float(scale[outside][0])} outside the factors "
                         f"{lo:g} to {hi:g} a render can show")  # fmt: skip
    out = K.clone()
    out[..., :2, :2] = K[..., :2, :2] * scale.to(K)[..., None, None]
    focal = out[..., [0, 1], [0, 1]]
    bad = ~(torch.isfinite(focal) & (focal > 0)).all(-1)
    if bad.any():
        i = tuple(int(j) for j in bad.nonzero()[0])
        raise ValueError(f"scale_focal: focal_scale {float(scale.expand(bad.shape)[i])} gives focal lengths "
                         f"{focal[i].tolist()} (of {K[i].diagonal()[:2].tolist()}), not finite positive "
                         f"{K.dtype} numbers")  # fmt: skip
    return out


def axis_rotation(axis: str | torch.Tensor, theta_deg: float | torch.Tensor, dtype=torch.float64,
                  device=None) -> torch.Tensor:
    """(..., 3, 3) rotations by ``theta_deg`` (degrees, float or (...)) about world axes
    (right-handed): ``axis`` is "x", "y" or "z", or (..., 3) unit directions. Kornia's
    axis-angle formula, element by element (a batch gives each element's own bits), of the angle
    modulo 360 deg (so that any finite angle is a rotation, in any dtype)."""
    if isinstance(axis, str):
        if axis not in AXES:
            raise ValueError(f"axis must be one of {AXES}, got {axis!r}")
        axis = torch.eye(3, dtype=dtype, device=device)[AXES.index(axis)]
    elif axis.shape[-1:] != (3,):
        raise ValueError(f"axis directions must be (..., 3), got {tuple(axis.shape)}")
    theta_deg = torch.fmod(torch.as_tensor(theta_deg, dtype=torch.float64, device=device), 360.0)  # exact
    theta = (theta_deg * (math.pi / 180)).to(dtype)
    axis = axis.to(dtype=dtype, device=theta.device)
    axis_angle = torch.where(axis == 0, torch.zeros((), dtype=dtype, device=theta.device), axis * theta[..., None])
    shape = axis_angle.shape[:-1]
    return axis_angle_to_rotation_matrix(axis_angle.reshape(-1, 3)).reshape(*shape, 3, 3)


def perturb_pose(c2w: torch.Tensor, pivot: torch.Tensor, axis: str | torch.Tensor, theta_deg: float | torch.Tensor,
                 mu_m: float | torch.Tensor, shift_m: torch.Tensor | None = None,
                 pivot_share: float | torch.Tensor = 1.0) -> torch.Tensor:  # fmt: skip
    """Move (..., 4, 4) OpenCV camera-to-world poses.

    R' = R_axis R, c' = q + R_axis (c - q) + shift + mu * R'[:, 2], with q = p + (1 - s) (c - p)
    the centre of the rotation: the pivot p ((3,) or (..., 3)) for the pivot share s = 1, the
    camera's centre c for s = 0; ``axis`` (see :func:`axis_rotation`), ``theta_deg``, ``mu_m``,
    ``shift_m`` ((3,) or (..., 3), default none) and ``pivot_share`` are one move or (...)
    moves, one per pose.

    Raises ``TypeError`` for poses that are not floating point, ``ValueError`` where a moved pose
    is not a finite rigid transform (:func:`_rigid`: a pose that was not one, or a move that is
    not finite in the poses' dtype).
    """
    _floating("perturb_pose", c2w)
    return _rigid("perturb_pose", _perturb_pose(c2w, pivot, axis, theta_deg, mu_m, shift_m, pivot_share))


def _perturb_pose(c2w: torch.Tensor, pivot: torch.Tensor, axis: str | torch.Tensor, theta_deg: float | torch.Tensor,
                  mu_m: float | torch.Tensor, shift_m: torch.Tensor | None = None,
                  pivot_share: float | torch.Tensor = 1.0) -> torch.Tensor:  # fmt: skip
    """:func:`perturb_pose`, unchecked."""
    Ra = axis_rotation(axis, theta_deg, c2w.dtype, c2w.device)
    p = torch.as_tensor(pivot, dtype=c2w.dtype, device=c2w.device)
    mu = torch.as_tensor(mu_m, dtype=c2w.dtype, device=c2w.device)
    share = torch.as_tensor(pivot_share, dtype=c2w.dtype, device=c2w.device)
    out = c2w.clone()
    R = Ra @ c2w[..., :3, :3]
    q = p + (1 - share)[..., None] * (c2w[..., :3, 3] - p)  # exactly p for a share of 1
    center = q + (Ra @ (c2w[..., :3, 3] - q)[..., None])[..., 0]
    if shift_m is not None:
        center = center + torch.as_tensor(shift_m, dtype=c2w.dtype, device=c2w.device)
    out[..., :3, :3] = R
    out[..., :3, 3] = center + mu[..., None] * R[..., :, 2]
    return out


def move_rig(c2w: torch.Tensor, moves: torch.Tensor, views: Sequence[int], pivot_depth: float | None = None
             ) -> torch.Tensor:  # fmt: skip
    """(..., R, 4, 4) poses of the cameras ``views`` (R indices) of rigs of (..., V, 4, 4)
    camera-to-world poses, each moved about its rig's pivot (:func:`rig_pivot`) by its move of
    the (..., R, :data:`ROW`) ``moves`` (:meth:`Perturbation.as_row`; their focal lengths:
    :func:`scale_focal`): what :meth:`Perturbation.move` does to one camera, for any batch of
    rigs (the batch path moves a whole training batch's cameras with it).

    Example: the left camera of a rig turned 5 deg about world X
        >>> from gensplat_transforms import look_at
        >>> rig = torch.stack([look_at((1.0, 0.3, 0.5), (0, 0, 0)), look_at((1.0, -0.3, 0.5), (0, 0, 0))])
        >>> move_rig(rig, torch.tensor([Perturbation("x", 5.0).as_row()], dtype=torch.float64), [0]).shape
        torch.Size([1, 4, 4])

    Raises as :func:`perturb_pose` does.
    """
    _floating("move_rig", c2w)
    return _rigid("move_rig", _move_rig(c2w, Moves.of_rows(moves.to(c2w.device)), views, pivot_depth))


def move_cameras(K: torch.Tensor, c2w: torch.Tensor, moves: torch.Tensor, views: Sequence[int],
                 pivot_depth: float | None = None) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """K (..., R, 3, 3) and c2w (..., R, 4, 4) of the cameras ``views`` (R indices) of rigs of
    (..., V, 3, 3) intrinsics ``K`` and (..., V, 4, 4) poses ``c2w``, each moved by its row of
    ``moves`` (..., R, :data:`ROW`): its pose by :func:`move_rig`, its focal length by
    :func:`scale_focal`. Raises as both do."""
    _floating("move_cameras", c2w)
    m = Moves.of_rows(moves.to(c2w.device))
    return scale_focal(K[..., list(views), :, :], m.focal_scale), _rigid("move_cameras", _move_rig(c2w, m, views,
                                                                                                  pivot_depth))


def _move_rig(c2w: torch.Tensor, moves: Moves, views: Sequence[int], pivot_depth: float | None = None
              ) -> torch.Tensor:  # fmt: skip
    """:func:`move_rig`, unchecked: the pivot and the moves in float64 (the pivot of nearly
    parallel axes loses digits in a coarser dtype), the poses returned in ``c2w``'s dtype. The
    pivot is found only when a move turns about it: moves about the cameras' own centres need
    none (so a one-camera rig needs no ``pivot_depth`` for them; a given one is still checked)."""
    pose = c2w.to(torch.float64)
    if pivot_depth is not None:
        _check_pivot_depth(pivot_depth)
    if bool((moves.pivot == 0).all()):
        pivot = pose[..., list(views), :3, 3]  # (..., R, 3): each camera's own centre
    else:
        pivot = rig_pivot(pose, pivot_depth)[..., None, :]  # (..., 1, 3)
    return _perturb_pose(pose[..., list(views), :, :], pivot, moves.axis, moves.theta_deg, moves.mu_m, moves.shift_m,
                         moves.pivot).to(c2w.dtype)  # fmt: skip


def _floating(name: str, c2w: torch.Tensor) -> None:
    """Raise ``TypeError`` naming ``name`` unless the poses ``c2w`` are floating point."""
    if not c2w.is_floating_point():
        raise TypeError(f"{name}: poses must be floating point, got {c2w.dtype}")


def _rigid(name: str, c2w: torch.Tensor) -> torch.Tensor:
    """The (..., 4, 4) moved poses ``c2w``, or ``ValueError`` naming ``name`` unless each is a
    finite rigid transform (:func:`.cameras._check_rigid`, to :func:`.cameras.rigid_tolerance`)."""
    T = c2w.detach().reshape(-1, 4, 4).to("cpu", torch.float64).numpy()
    try:
        if not np.isfinite(T).all():
            raise ValueError("not finite")
        _check_rigid(T, rigid_tolerance(c2w.dtype))
    except ValueError as e:
        raise ValueError(f"{name}: the moved poses are not finite rigid transforms ({e}): the poses must be "
                         f"rigid and the moves finite in {c2w.dtype}") from None  # fmt: skip
    return c2w


def closest_points_between_axes(
    c2w_a: torch.Tensor, c2w_b: torch.Tensor, parallel_tol: float = 1e-6
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Closest points on the two optical axes (infinite lines), or None when parallel."""
    pa, pb, denom = _closest(c2w_a, c2w_b)
    return None if denom < parallel_tol else (pa, pb)


def rig_pivot(c2w: torch.Tensor, pivot_depth: float | None = None) -> torch.Tensor:
    """(..., 3) pivot of rigs of (..., V, 4, 4) camera poses: :func:`pivot_point` of cameras 0
    and 1, or, with ``pivot_depth`` (a rig of one camera needs it), the point ``pivot_depth``
    metres along camera 0's optical axis.

    Example: one camera at the origin looking along +z
        >>> rig_pivot(torch.eye(4, dtype=torch.float64)[None], pivot_depth=0.8)
        tensor([0.0000, 0.0000, 0.8000], dtype=torch.float64)
    """
    if pivot_depth is None and c2w.shape[-3] > 1:
        return pivot_point(c2w[..., 0, :, :], c2w[..., 1, :, :])
    _check_pivot_depth(pivot_depth)
    axis = c2w[..., 0, :3, 2]
    return c2w[..., 0, :3, 3] + pivot_depth * axis / axis.norm(dim=-1, keepdim=True)


def _check_pivot_depth(pivot_depth: float | None) -> None:
    """Raise ``ValueError`` unless ``pivot_depth`` is a finite positive distance."""
    if pivot_depth is None or not (math.isfinite(pivot_depth) and pivot_depth > 0):
        raise ValueError(f"rig_pivot: pivot_depth must be a positive distance in metres along camera 0's optical "
                         f"axis (a rig of one external camera needs one), got {pivot_depth}")  # fmt: skip


#: Seeds and indices of a draw lie below 2**32: NumPy splits a larger integer of a seed's key
#: into 32-bit words, so (2**32, 5) would draw what (0, 1, 5) draws.
KEY_LIMIT = 2**32


class _Sampler:
    """Seeded draws per (episode, frame, view): ``mode="episode"`` gives every frame of an
    episode the same move, ``"frame"`` a new one per frame; ``focal_scale`` (low, high) adds a
    focal-length change drawn log-uniformly (none when (1, 1))."""

    #: salt of the seed, so that samplers of one seed draw apart (None: the paper's, unsalted)
    salt: int | None = None
    #: whether its moves turn about the rig's pivot (False: about each camera's own centre,
    #: so a one-camera rig needs no ``pivot_depth`` for them)
    about_pivot: bool = True

    def __init__(self, mode: str = "episode", seed: int = 0, focal_scale: tuple[float, float] = (1.0, 1.0)) -> None:
        if mode not in ("episode", "frame"):
            raise ValueError(f"{type(self).__name__}.mode must be 'episode' or 'frame', got {mode!r}")
        seed = _integer(f"{type(self).__name__}.seed", seed)
        if not 0 <= seed < KEY_LIMIT:
            raise ValueError(f"{type(self).__name__}.seed must be in [0, 2**32), got {seed}")
        self.mode, self.seed = mode, seed
        self.focal_scale = _focal_range(f"{type(self).__name__}.focal_scale", focal_scale)

    def sample(self, episode_index: int, frame_index: int = 0, view: int = 0) -> Perturbation:
        name = f"{type(self).__name__}.sample: "
        key = [self.seed, _integer(name + "episode_index", episode_index),
               _integer(name + "frame_index", frame_index) if self.mode == "frame" else 0, _integer(name + "view", view)]
        if not 0 <= min(key) <= max(key) < KEY_LIMIT:
            raise ValueError(f"{type(self).__name__}.sample: episode/frame/view indices must be in [0, 2**32), "
                             f"got {key[1:]}")  # fmt: skip
        rng = np.random.default_rng(key if self.salt is None else [*key, self.salt])
        move = self._draw(rng)
        if self.focal_scale == (1.0, 1.0):
            return move
        lo, hi = self.focal_scale
        scale = math.exp(rng.uniform(math.log(lo), math.log(hi)))
        return replace(move, focal_scale=min(max(scale, lo), hi))  # exp(log(x)) may round past x

    def _draw(self, rng: np.random.Generator) -> Perturbation:
        raise NotImplementedError


class PaperSampler(_Sampler):
    """The paper's sampler (formerly ``PerturbationSampler``): rotation about world X or Y
    (``axes``) through the pivot, then a forward step, drawn from ``level``'s ranges.

    ``mode="episode"`` (the paper's default) gives every frame of an episode the same
    perturbation, so an augmented trajectory shares one camera; ``mode="frame"`` draws a
    new one per frame. ``view`` selects one of several augmented views of the same source
    (the paper's saturation study uses about three per trajectory).

    Example:
        >>> s = PaperSampler("large", seed=0)
        >>> s.sample(episode_index=3) == s.sample(episode_index=3, frame_index=10)
        True
    """

    def __init__(self, level: str | PerturbationRange = "train", mode: str = "episode", seed: int = 0,
                 axes: tuple[str, ...] = PAPER_AXES, focal_scale: tuple[float, float] = (1.0, 1.0)) -> None:  # fmt: skip
        super().__init__(mode, seed, focal_scale)
        bad = [a for a in axes if a not in PAPER_AXES]
        if bad or not axes:
            raise ValueError(f"PaperSampler.axes must be a non-empty subset of {PAPER_AXES}, got {axes}")
        self.range = get_range(level)
        self.axes = tuple(axes)

    def _draw(self, rng: np.random.Generator) -> Perturbation:
        axis = self.axes[int(rng.integers(len(self.axes)))]
        theta = float(rng.uniform(*self.range.theta_deg))
        if self.range.random_sign and rng.random() < 0.5:
            theta = -theta
        mu = float(rng.uniform(*self.range.mu_m))
        return Perturbation(axis=axis, theta_deg=theta + 0.0, mu_m=mu)


class _Turns(_Sampler):
    """A sampler of turns by up to ``limit_deg`` either way and shifts by up to ``shift_m``."""

    def __init__(self, limit_deg: float, shift_m: float = 0.03, mode: str = "episode", seed: int = 0,
                 focal_scale: tuple[float, float] = (1.0, 1.0)) -> None:  # fmt: skip
        super().__init__(mode, seed, focal_scale)
        self.limit_deg = _non_negative(f"{type(self).__name__}.limit_deg", limit_deg, 180.0)
        self.shift_m = _non_negative(f"{type(self).__name__}.shift_m", shift_m)


class TiltSampler(_Turns):
    """The camera turned about a uniformly random world axis through its own centre by up to
    ``limit_deg`` either way (uniform), and shifted in the world uniformly in [-``shift_m``,
    ``shift_m``] per axis: a bumped or remounted camera, the kind of move VISTA's
    ``small_perturb`` evaluates (over a box rather than its Gaussians). Unlike the turns about
    the pivot, these move the image: 10 deg is about a sixth of a 60 deg field of view.

    Example:
        >>> p = TiltSampler(limit_deg=10.0, shift_m=0.03, seed=0).sample(episode_index=2)
        >>> abs(p.theta_deg) <= 10.0 and max(abs(v) for v in p.shift_m) <= 0.03
        True
    """

    salt = 1
    about_pivot = False

    def _draw(self, rng: np.random.Generator) -> Perturbation:
        axis = rng.normal(size=3)  # a normalised isotropic Gaussian: uniform on the sphere
        theta = float(rng.uniform(-self.limit_deg, self.limit_deg))
        shift = rng.uniform(-self.shift_m, self.shift_m, 3)
        return Perturbation(tuple(axis.tolist()), theta + 0.0, 0.0, tuple(shift.tolist()), about="camera")


class ArcSampler(_Turns):
    """Turns about the world's vertical (+z) through the pivot by up to ``limit_deg`` either
    way (uniform), and a step along the viewing axis uniform in [-``shift_m``, ``shift_m``]:
    the camera moved along an arc around the scene, as VISTA's ``arc_90deg`` evaluates (its
    +-45 deg is ``limit_deg=45``). The world must have +z up (the simulated, the estimated and
    DROID's calibrations do).

    Example:
        >>> p = ArcSampler(limit_deg=45.0, seed=0).sample(episode_index=2)
        >>> p.axis, abs(p.theta_deg) <= 45.0
        ('z', True)
    """

    salt = 2

    def _draw(self, rng: np.random.Generator) -> Perturbation:
        theta = float(rng.uniform(-self.limit_deg, self.limit_deg))
        return Perturbation("z", theta + 0.0, float(rng.uniform(-self.shift_m, self.shift_m)))


class MixSampler(_Sampler):
    """Each move from one of ``samplers`` chosen uniformly, drawn from that sampler's ranges
    with this sampler's seed, mode and focal change (those of ``samplers`` are not used): a
    training mix of the paper's moves, tilts and arcs.

    Example:
        >>> s = MixSampler((PaperSampler("train"), TiltSampler(10.0), ArcSampler(45.0)), seed=0)
        >>> sorted({str(s.sample(ep).axis)[:1] for ep in range(50)})  # x, y (paper), z (arc), ( (tilt)
        ['(', 'x', 'y', 'z']
    """

    salt = 3

    def __init__(self, samplers: Sequence[_Sampler], mode: str = "episode", seed: int = 0,
                 focal_scale: tuple[float, float] = (1.0, 1.0)) -> None:  # fmt: skip
        super().__init__(mode, seed, focal_scale)
        self.samplers = tuple(samplers)
        if not self.samplers:
            raise ValueError("MixSampler: needs at least one sampler")
        wrong = [type(s).__name__ for s in self.samplers if not isinstance(s, _Sampler)]
        if wrong:
            raise TypeError(f"MixSampler: samplers must be samplers (PaperSampler, TiltSampler, ...), got {wrong}")

    @property
    def about_pivot(self) -> bool:
        """Whether any of its samplers turns about the rig's pivot."""
        return any(s.about_pivot for s in self.samplers)

    def _draw(self, rng: np.random.Generator) -> Perturbation:
        return self.samplers[int(rng.integers(len(self.samplers)))]._draw(rng)


def _non_negative(name: str, value: float, most: float = math.inf) -> float:
    """``value`` as a float, or an error naming ``name`` unless it is a finite number in [0,
    most] that can be drawn from [-value, value]."""
    value = _real(name, value)
    if not (math.isfinite(value) and 0 <= value <= most):
        raise ValueError(f"{name} must be a finite number in [0, {most:g}], got {value}")
    if not math.isfinite(2 * value):
        raise ValueError(f"{name} must be at most {sys.float_info.max / 2:g} (to draw from [-{name}, {name}]), "
                         f"got {value}")  # fmt: skip
    return value


def sampler_kinds(kind: str) -> tuple[str, ...]:
    """The kinds of move (of :data:`KINDS`) the sampler ``kind`` draws (see :func:`make_sampler`),
    or ValueError naming it unless it is one of :data:`SAMPLERS` or kinds separated by commas."""
    kinds = KINDS if kind == "mix" else tuple(k.strip() for k in kind.split(",")) if isinstance(kind, str) else ()
    if not kinds or not set(kinds) <= set(KINDS) or len(set(kinds)) < len(kinds):
        raise ValueError(f"unknown perturbation sampler {kind!r}; choose one of {SAMPLERS}, or several of {KINDS} "
                         f"separated by commas, each once (e.g. 'tilt,arc')")  # fmt: skip
    return kinds


def make_sampler(kind: str = "paper", level: str | PerturbationRange = "train", mode: str = "episode", seed: int = 0,
                 tilt_deg: float = 10.0, arc_deg: float = 45.0, shift_m: float = 0.03,
                 focal_scale: tuple[float, float] = (1.0, 1.0)) -> _Sampler:  # fmt: skip
    """The sampler ``kind`` with its settings: "paper" draws from ``level``, "tilt" from
    ``tilt_deg`` and ``shift_m``, "arc" from ``arc_deg`` and ``shift_m``; "mix", or several
    kinds separated by commas ("tilt,arc"), one of those kinds per move (:class:`MixSampler`;
    "mix" is "paper,tilt,arc"); every kind adds ``focal_scale``. Every setting is checked,
    under its own name, whichever kind uses it.

    Example:
        >>> sorted({make_sampler("tilt,arc", seed=1).sample(ep).about for ep in range(20)})
        ['camera', 'pivot']
    """
    _non_negative("tilt_deg", tilt_deg, 180.0), _non_negative("arc_deg", arc_deg, 180.0)
    _non_negative("shift_m", shift_m), _focal_range("focal_scale", focal_scale)
    kinds = sampler_kinds(kind)
    make = {"paper": lambda **kw: PaperSampler(level, **kw), "tilt": lambda **kw: TiltSampler(tilt_deg, shift_m, **kw),
            "arc": lambda **kw: ArcSampler(arc_deg, shift_m, **kw)}  # fmt: skip
    settings = {"mode": mode, "seed": seed, "focal_scale": focal_scale}
    if len(kinds) == 1:
        return make[kinds[0]](**settings)
    return MixSampler([make[k]() for k in kinds], **settings)

__getattr__ = renamed(__name__)  # the former PerturbationSampler
