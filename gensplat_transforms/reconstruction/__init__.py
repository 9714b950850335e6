"""Reconstructors: the views of one timestep in, 3D Gaussians out."""

from .base import DepthReconstructor, Reconstruction, Reconstructor, Views
from .model import GenSplatReconstructor
from .rgbd import RGBDConfig, RGBDReconstructor

__all__ = [
    "DepthReconstructor",
    "GenSplatReconstructor",
    "RGBDConfig",
    "RGBDReconstructor",
    "Reconstruction",
    "Reconstructor",
    "Views",
]
