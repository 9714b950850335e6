"""One item's views planned once: whether it is augmented and how each replaced camera moves.

:meth:`.transform.GenSplatTransform.plan` draws a :class:`ViewPlan` (torch's RNG and the
transform's perturbation sampler) and ``transform(item, plan=...)`` replays one. The worker
path renders the plan's moves; with ``render_in="batch"`` the item carries them
(``BATCH_KEYS``) and :func:`.batched.render_batch` moves the cameras of the whole batch with
the same function (:func:`.perturbation.move_rig`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from .perturbation import Perturbation

#: item keys the transform adds with ``render_in="batch"`` and ``render_batch`` removes:
#: ``gensplat.render`` () bool, the item is augmented; ``gensplat.depth`` (T, V, h, w) int16,
#: the stored depth of the stack's T frames and V reconstructed cameras, uncleaned, at the render
#: size where it fits in the stored size, else at that (the batch side takes the nearest pixels);
#: ``gensplat.coded`` () bool, log codes or float16 bits (:func:`.depth_codec.depth_from_words`);
#: ``gensplat.K`` (T, V, 3, 3) and ``gensplat.c2w`` (T, V, 4, 4) float64, the cached cameras
#: (intrinsics at the render size); ``gensplat.moves`` (R, 3) float64, :meth:`ViewPlan.moves_tensor`
BATCH_KEYS = ("gensplat.render", "gensplat.depth", "gensplat.coded", "gensplat.K", "gensplat.c2w", "gensplat.moves")


@dataclass(frozen=True)
class ViewPlan:
    """The draws that make one item's views.

    Attributes:
        applied: whether the item's replaced cameras are replaced.
        moves: one :class:`.perturbation.Perturbation` per replaced camera
            (``GenSplatConfig.replace`` order); no move where not applied.

    Example:
        >>> plan = ViewPlan(True, (Perturbation("x", 5.0, 0.02), Perturbation("y", -3.0, 0.0)))
        >>> plan.moves_tensor()
        tensor([[ 0.0000,  5.0000,  0.0200],
                [ 1.0000, -3.0000,  0.0000]], dtype=torch.float64)
    """

    applied: bool
    moves: tuple[Perturbation, ...]

    def __post_init__(self) -> None:
        if not isinstance(self.applied, bool):
            raise TypeError(f"ViewPlan.applied must be a bool, got {type(self.applied).__name__}")
        object.__setattr__(self, "moves", tuple(self.moves))
        wrong = [type(p).__name__ for p in self.moves if not isinstance(p, Perturbation)]
        if wrong:
            raise TypeError(f"ViewPlan.moves must be Perturbations (one per replaced camera), got {wrong}")

    def moves_tensor(self) -> torch.Tensor:
        """(R, 3) float64 moves, each :meth:`.perturbation.Perturbation.as_row`."""
        return torch.tensor([p.as_row() for p in self.moves], dtype=torch.float64).reshape(len(self.moves), 3)

    def report(self) -> dict[str, torch.Tensor]:
        """The ``gensplat.*`` keys that describe the plan (``GenSplatConfig.report``):
        applied (R,) bool, axis (R,) long, theta_deg (R,) and mu_m (R,) float32; all zero
        where not applied."""
        r = torch.tensor([[1.0, *row] for row in self.moves_tensor().tolist()]) if self.applied else \
            torch.zeros(len(self.moves), 4)  # fmt: skip
        return {"gensplat.applied": r[:, 0].bool(), "gensplat.axis": r[:, 1].long(),
                "gensplat.theta_deg": r[:, 2], "gensplat.mu_m": r[:, 3]}  # fmt: skip
