"""The cache stage: what a reconstructor made of every timestep, stored per episode.

:mod:`.store` (``SceneCache``: one file per episode, built under a lock, read within a
memory budget), :mod:`.format` (what an episode file holds: encoders, checksums,
``EpisodeFile``), :mod:`.depth_codec` (the depth's bounded-error compression),
:mod:`.builder` (``build_cache``: every episode of a source, and the built-in scene's
episodes), :mod:`.distributed` (one shard of the episodes per process) and :mod:`.reader`
(``CacheReader``: the transform's reads, frames stacked and clamped to the episode). Imports
only the core, data and geometry stages.
"""

from ..core.renamed import renamed
from .builder import build_cache
from .reader import CacheReader
from .store import EpisodeSource, SceneCache

__all__ = ["CacheReader", "EpisodeSource", "SceneCache", "build_cache"]

__getattr__ = renamed(__name__)  # the former GaussianCache
