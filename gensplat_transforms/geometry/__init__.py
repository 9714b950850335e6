"""The geometry stage: reconstructors, the calibrated views of one timestep in, 3D Gaussians out.

:mod:`.base` (the ``Reconstructor`` protocol; ``Views`` and ``Reconstruction`` come from the
core), :mod:`.rgbd` (surface discs from RGB-D, compiled twin :mod:`.discs_fast`, depth holes
:mod:`.depth_fill`), :mod:`.geometry` (depth from a Pi3-compatible or DA3 model, then discs),
:mod:`.monocular` (one image at a time: MoGe-2's metric depth, then discs),
:mod:`.feedforward` (the GenSplat model's own Gaussians), :mod:`.registry`
(``make_reconstructor``: one by name) and :mod:`.model` (the network itself). Entry points:
``make_reconstructor`` and each reconstructor's ``reconstruct(views)``. Imports only the core
and the data stage.
"""

from .base import DepthReconstructor, Reconstruction, Reconstructor, Views
from .feedforward import GenSplatReconstructor
from .geometry import GeometryReconstructor
from .monocular import MonocularReconstructor
from .registry import RECONSTRUCTORS, make_reconstructor
from .rgbd import RGBDConfig, RGBDReconstructor

__all__ = [
    "RECONSTRUCTORS",
    "DepthReconstructor",
    "GenSplatReconstructor",
    "GeometryReconstructor",
    "MonocularReconstructor",
    "RGBDConfig",
    "RGBDReconstructor",
    "Reconstruction",
    "Reconstructor",
    "Views",
    "make_reconstructor",
]
