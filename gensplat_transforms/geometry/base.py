"""The reconstructor interface: several views of one timestep in, one set of Gaussians out."""

from __future__ import annotations

import hashlib
import json
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator

from ..core.views import MAX_VIEW_DEPTH, Reconstruction, Views, nearest_pixels, valid_depth

__all__ = ["MAX_VIEW_DEPTH", "DepthReconstructor", "Reconstruction", "Reconstructor", "Views", "nearest_pixels",
           "valid_depth"]  # fmt: skip

class Reconstructor(ABC):
    """Turns the views of one timestep into Gaussians.

    Subclasses set ``name`` and implement :meth:`reconstruct` and :meth:`config`; the
    identity string (name + hash of the config) tells caches when their content is stale.
    """

    name: str = "reconstructor"

    @abstractmethod
    def reconstruct(self, views: Views) -> Reconstruction: ...

    @abstractmethod
    def config(self) -> dict: ...

    def identity(self) -> str:
        blob = json.dumps({"name": self.name, **self.config()}, sort_keys=True).encode()
        return f"{self.name}-{hashlib.sha256(blob).hexdigest()[:16]}"

    def __call__(self, views: Views) -> Reconstruction:
        return self.reconstruct(views)


class DepthReconstructor(Reconstructor):
    """A reconstructor whose Gaussians follow cheaply from the images, the cameras and one
    depth map per view. The work splits in two, and caches store only what is between:

    * :meth:`predict_depth` (expensive: a model's forward pass, or reading sensor depth):
      views -> the same views with ``cameras`` and ``depths`` set (0 where no Gaussian);
      :meth:`predict_depths` does it for many timesteps (a cache build), which a model may
      batch;
    * :meth:`assemble` (cheap, runs in dataloader workers): such views -> Gaussians.

    ``given_depth``: :meth:`predict_depth` returns the views' own depth cleaned by the
    reconstructor's ``clean_depth(depths)``, so a cache may read that depth from the dataset
    and clean it instead of storing it.
    """

    given_depth = False

    @abstractmethod
    def predict_depth(self, views: Views) -> Views: ...

    def predict_depths(self, views: Iterable[Views]) -> Iterator[Views]:
        """:meth:`predict_depth` of each of ``views`` (timesteps, in order), yielded as they come:
        the views are read lazily, so that a caller consuming the results one at a time holds
        one timestep (a batching subclass: one batch). Subclasses may run several timesteps at
        once; what they yield must be what :meth:`predict_depth` returns, but for a scale
        aligned across the run's frames where a single timestep's is its own (the monocular
        reconstructor's)."""
        for v in views:
            yield self.predict_depth(v)

    @abstractmethod
    def assemble(self, views: Views) -> Reconstruction: ...

    def reconstruct(self, views: Views) -> Reconstruction:
        return self.assemble(self.predict_depth(views))
