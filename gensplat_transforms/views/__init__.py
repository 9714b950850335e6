"""The view-plan stage: how each augmented view's camera moves.

:mod:`.perturbation` (the perturbation protocol: ``PaperSampler`` and the other
samplers, ``make_sampler``, ``Perturbation`` and its ``move`` about the rig's pivot,
``Moves`` (a batch of moves by name), ``move_rig`` and ``move_cameras`` for a batch, the named ``LEVELS``) and :mod:`.plan` (``ViewPlan``: whether an
item is augmented and each replaced camera's move, drawn once and replayable). Imports only
the core; the transform's settings only as a type.
"""

from ..core.renamed import renamed
from .perturbation import (
    LEVELS,
    Moves,
    PaperSampler,
    Perturbation,
    PerturbationRange,
    make_sampler,
    move_cameras,
    move_rig,
)
from .plan import ViewPlan

__all__ = ["LEVELS", "Moves", "PaperSampler", "Perturbation", "PerturbationRange", "ViewPlan", "make_sampler",
           "move_cameras", "move_rig"]

__getattr__ = renamed(__name__)  # the former PerturbationSampler
