"""The core: the types and helpers every stage shares.

Cameras (:mod:`.cameras`: ``Cameras``, ``look_at``, ``pivot_point``), Gaussians
(:mod:`.gaussians`), rotations and spherical harmonics (:mod:`.rotations`, :mod:`.sh`), the
views of one timestep and what a reconstructor makes of them (:mod:`.views`: ``Views``,
``Reconstruction``), atomic writes (:mod:`.atomic`), checked tensors (:mod:`.checked`),
sample counters (:mod:`.counters`), safetensors files read in place (:mod:`.tensor_file`),
image metrics (:mod:`.metrics`), image grids (:mod:`.images`) and numba's compiled-kernel
decorator (:mod:`.jit`). The core imports no other stage.
"""

from .cameras import Cameras, look_at, pivot_point
from .gaussians import Gaussians
from .views import Reconstruction, Views

__all__ = ["Cameras", "Gaussians", "Reconstruction", "Views", "look_at", "pivot_point"]
