"""gensplat-transforms: camera-pose augmentation for robot policy learning with 3D Gaussians."""

from .cameras import Cameras, look_at
from .gaussians import Gaussians
from .perturbation import LEVELS, Perturbation, PerturbationRange, PerturbationSampler, pivot_point
from .rendering import RenderOutput, render

__version__ = "0.1.0"

__all__ = [
    "LEVELS",
    "Cameras",
    "Gaussians",
    "Perturbation",
    "PerturbationRange",
    "PerturbationSampler",
    "RenderOutput",
    "look_at",
    "pivot_point",
    "render",
]
