"""The feed-forward GenSplat model (Pi3-compatible geometry + a DPT Gaussian head)."""

from .checkpoints import LoadReport, load_pi3_weights
from .config import PATCH_SIZE, ModelConfig
from .gensplat import GenSplatModel, to_gaussians

__all__ = ["PATCH_SIZE", "GenSplatModel", "LoadReport", "ModelConfig", "load_pi3_weights", "to_gaussians"]
