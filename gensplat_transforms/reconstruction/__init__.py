"""Reconstructors: the views of one timestep in, 3D Gaussians out."""

from .base import DepthReconstructor, Reconstruction, Reconstructor, Views
from .geometry import GeometryReconstructor
from .model import GenSplatReconstructor
from .registry import RECONSTRUCTORS, make_reconstructor
from .rgbd import RGBDConfig, RGBDReconstructor

__all__ = [
    "RECONSTRUCTORS",
    "DepthReconstructor",
    "GenSplatReconstructor",
    "GeometryReconstructor",
    "RGBDConfig",
    "RGBDReconstructor",
    "Reconstruction",
    "Reconstructor",
    "Views",
    "make_reconstructor",
]
