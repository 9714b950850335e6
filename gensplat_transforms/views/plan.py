"""One item's views planned once: whether it is augmented and how each replaced camera moves.

:meth:`ViewPlan.draw` draws a plan (torch's RNG and the transform's perturbation sampler;
:meth:`.transform.GenSplatTransform.plan` draws an item's) and ``transform(item, plan=...)``
replays one. The worker path renders the plan's moves; with ``render_in="batch"`` the item
carries them (``BATCH_KEYS``) and :func:`.batched.render_batch` moves the cameras of the whole
batch with the same function (:func:`.perturbation.move_rig`).
"""

from __future__ import annotations

import operator
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
import torch

from .perturbation import Perturbation

if TYPE_CHECKING:
    from ..settings import GenSplatConfig

#: item keys the transform adds with ``render_in="batch"`` and ``render_batch`` removes:
#: ``gensplat.render`` () bool, the item is augmented; ``gensplat.depth`` (T, V, h, w) int16,
#: the stored depth of the stack's T frames and V reconstructed cameras, uncleaned, at the render
#: size where it fits in the stored size, else at that (the batch side takes the nearest pixels);
#: ``gensplat.coded`` () bool, log codes or float16 bits (:func:`.depth_codec.depth_from_words`);
#: ``gensplat.K`` (T, V, 3, 3) and ``gensplat.c2w`` (T, V, 4, 4) float64, the cached cameras
#: (intrinsics at the render size); ``gensplat.moves`` (R, ``perturbation.ROW``) float64,
#: :attr:`ViewPlan.rows`
BATCH_KEYS = ("gensplat.render", "gensplat.depth", "gensplat.coded", "gensplat.K", "gensplat.c2w", "gensplat.moves")


@dataclass(frozen=True)
class ViewPlan:
    """The draws that make one item's views.

    Attributes:
        applied: whether the item's replaced cameras are replaced.
        moves: one :class:`.perturbation.Perturbation` per replaced camera
            (``GenSplatConfig.replace`` order); no move where not applied.
        rows: the R moves as rows of floats, each :meth:`.perturbation.Perturbation.as_row`
            (what the item's keys carry).

    Example:
        >>> plan = ViewPlan(True, (Perturbation("x", 5.0, 0.02), Perturbation("y", -3.0, 0.0)))
        >>> plan.rows[0]  # axis direction, theta_deg, mu_m, shift_m, focal_scale, pivot share
        (1.0, 0.0, 0.0, 5.0, 0.02, 0.0, 0.0, 0.0, 1.0, 1.0)
    """

    applied: bool
    moves: tuple[Perturbation, ...]
    rows: tuple[tuple[float, ...], ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.applied, bool):
            raise TypeError(f"ViewPlan.applied must be a bool, got {type(self.applied).__name__}")
        object.__setattr__(self, "moves", tuple(self.moves))
        wrong = [type(p).__name__ for p in self.moves if not isinstance(p, Perturbation)]
        if wrong:
            raise TypeError(f"ViewPlan.moves must be Perturbations (one per replaced camera), got {wrong}")
        object.__setattr__(self, "rows", tuple(tuple(float(v) for v in p.as_row()) for p in self.moves))

    @classmethod
    def draw(cls, config: GenSplatConfig, sampler, episode: int, frame: int, view: int | None = None) -> ViewPlan:
        """The plan of frame ``frame`` of ``episode``: augmented with ``config.probability`` and
        which of ``config.views_per_source`` moves (torch's RNG, which DataLoader seeds per
        worker; ``view`` picks one, 0 .. views_per_source - 1), each replaced camera's move
        from ``sampler`` (``GenSplatConfig.perturbations``)."""
        if view is not None:
            view = _view_index(view, config.views_per_source)
        applied = bool(torch.rand(()) < config.probability)
        view = int(torch.randint(config.views_per_source, ())) if view is None else view
        R = len(config.replace)
        return cls(applied, tuple(sampler.sample(episode, frame, view=view * R + ci) if applied else Perturbation()
                                  for ci in range(R)))  # fmt: skip


def _view_index(view, views: int) -> int:
    """``view`` as an int in 0 .. ``views`` - 1: any integer type (Python, NumPy, a 0-d integer
    tensor), never a boolean; else ``ValueError``."""
    boolean = isinstance(view, (bool, np.bool_)) or (isinstance(view, torch.Tensor) and view.dtype == torch.bool)
    try:
        index = None if boolean else operator.index(view)
    except TypeError:
        index = None
    if index is None or not 0 <= index < views:
        raise ValueError(f"ViewPlan.draw: view must be an integer in 0..{views - 1} (views_per_source), got {view!r}")
    return index
