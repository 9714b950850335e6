"""Reconstructors: the views of one timestep in, 3D Gaussians out."""

from .base import Reconstruction, Reconstructor, Views
from .rgbd import RGBDConfig, RGBDReconstructor

__all__ = ["RGBDConfig", "RGBDReconstructor", "Reconstruction", "Reconstructor", "Views"]
