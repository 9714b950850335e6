"""gensplat-transforms: camera-pose augmentation for robot policy learning with 3D Gaussians.

The public API: cameras and Gaussians (:class:`Cameras`, :func:`look_at`, :class:`Gaussians`),
the perturbation protocol (:class:`PaperSampler`, :class:`PerturbationRange`,
:class:`Perturbation`, :func:`pivot_point`, :data:`LEVELS`), reconstructors (:class:`Views` in,
Gaussians out: :class:`RGBDReconstructor`, :class:`GeometryReconstructor`,
:class:`GenSplatReconstructor`, :func:`make_reconstructor`), :func:`render`, the cache
(:class:`SceneCache`, :func:`build_cache`) and the online transform
(:class:`GenSplatTransform`, :class:`GenSplatConfig`, :class:`AugmentedDataset`, and
:func:`render_batch` for ``render_in="batch"``). The simulator (``gensplat_sim``)
and LeRobot (``gensplat_lerobot``) are imported only where used.

Example: two calibrated RGB-D views of one timestep, seen from a camera moved at "large":
    >>> from gensplat_transforms import PaperSampler, RGBDReconstructor, Views, render
    >>> from gensplat_transforms.data.scenes import TabletopScene, default_cameras
    >>> cameras = default_cameras(32, 32)[:2]
    >>> images, depths = TabletopScene(seed=1).render(cameras)
    >>> recon = RGBDReconstructor().reconstruct(Views(images, cameras, depths))
    >>> moved = PaperSampler("large", seed=0).sample(episode_index=7).move(cameras, 0)
    >>> render(recon.gaussians, moved, backend="fast").rgb.shape
    torch.Size([1, 3, 32, 32])
"""

from .cache.builder import build_cache
from .cache.store import SceneCache
from .core.cameras import Cameras, look_at
from .core.gaussians import Gaussians
from .core.renamed import renamed
from .geometry import (
    GenSplatReconstructor,
    GeometryReconstructor,
    RGBDReconstructor,
    Views,
    make_reconstructor,
)
from .rendering import RenderOutput, render
from .rendering.batched import render_batch
from .transform import AugmentedDataset, GenSplatConfig, GenSplatTransform
from .views.perturbation import LEVELS, PaperSampler, Perturbation, PerturbationRange, pivot_point

__version__ = "0.1.0"

__all__ = [
    "LEVELS",
    "AugmentedDataset",
    "Cameras",
    "Gaussians",
    "GenSplatConfig",
    "GenSplatReconstructor",
    "GenSplatTransform",
    "GeometryReconstructor",
    "PaperSampler",
    "Perturbation",
    "PerturbationRange",
    "RGBDReconstructor",
    "RenderOutput",
    "SceneCache",
    "Views",
    "build_cache",
    "look_at",
    "make_reconstructor",
    "pivot_point",
    "render",
    "render_batch",
]

__getattr__ = renamed(__name__)  # the former GaussianCache and PerturbationSampler
