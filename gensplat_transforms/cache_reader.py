"""What the transform reads from a cache, and nothing else.

:class:`CacheReader` answers the three questions a dataset item asks (how many frames its
episode has; one timestep's Gaussians at a size; the stored depth of a stack of frames for the
batch path) and owns what reading implies: an episode that is missing is built from the source
(safe with several workers), and one whose data fails its checksum is rebuilt once. How the
cache stores a timestep (Gaussians, or depth from which Gaussians are rebuilt) stays inside it:
the reader asks the caller for the item's images only when the storage needs them.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from .cache import CorruptCacheError, EpisodeSource, GaussianCache
from .views import Reconstruction, nearest_pixels

logger = logging.getLogger(__name__)


@dataclass
class DepthStack:
    """The stored depth of T timesteps of V cameras, for :func:`.batched.render_batch`.

    Attributes:
        words: (T, V, h, w) int16, as the cache stores it (:func:`.depth_codec.depth_from_words`).
        coded: whether the words are log codes (else float16 bits).
        K: (T, V, 3, 3) float64 intrinsics at the size asked for; c2w: (T, V, 4, 4) float64.
    """

    words: torch.Tensor
    coded: bool
    K: torch.Tensor
    c2w: torch.Tensor


class CacheReader:
    """Reads ``cache`` for a transform, building its missing episodes from ``source`` (none:
    a missing episode raises FileNotFoundError) and rebuilding an episode once when its data
    fails a checksum (with a source; without, the CorruptCacheError is raised).

    Example:
        >>> import tempfile
        >>> from gensplat_transforms import RGBDReconstructor
        >>> from gensplat_transforms.episodes import SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=3, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> reader = CacheReader(GaussianCache(folder.name, RGBDReconstructor(), source.fingerprint), source)
        >>> reader.frames(0)  # built on first use
        3
        >>> rec = reader.timestep(0, 2, (16, 16), lambda: source.views(0, 2).images)
        >>> len(rec.cameras), reader.depth(0, [1, 2], (8, 8)).words.shape  # (T, V, h, w)
        (2, torch.Size([2, 2, 8, 8]))
        >>> folder.cleanup()
    """

    def __init__(self, cache: GaussianCache, source: EpisodeSource | None = None) -> None:
        self.cache = cache
        self.source = source

    def __str__(self) -> str:
        return f"the cache at {self.cache.root} ({self.cache.identity})"

    @property
    def batchable(self) -> bool:
        """Whether :meth:`depth` can serve the batch path: the cache stores depth (from which
        the batch side rebuilds the Gaussians), not Gaussians."""
        return self.cache.kind == "depth"

    def frames(self, episode: int) -> int:
        """The number of frames of ``episode``, built first if the cache lacks it."""
        self._ensure(episode)
        return self.cache.num_frames(episode)

    def timestep(self, episode: int, frame: int, size: tuple[int, int],
                 images: Callable[[], torch.Tensor]) -> Reconstruction:  # fmt: skip
        """The Gaussians and source cameras of one timestep at ``size`` = (width, height) (see
        :meth:`.GaussianCache.read`); ``images()`` gives the reconstructed cameras' images of
        this timestep, (V, 3, h, w) float in [0, 1] at ``size``, and is called only where the
        cache rebuilds the Gaussians from them."""
        given = images() if self.cache.kind == "depth" else None
        return self._read(episode, lambda: self.cache.read(episode, frame, given, size))

    def depth(self, episode: int, frames: Sequence[int], size: tuple[int, int], read: bool = True) -> DepthStack:
        """The stored depth of ``frames`` of ``episode`` (T = len(frames)) for a render of
        ``size`` = (width, height): at that size (the stored pixels nearest its pixel centres)
        where it fits in the stored size, else at the stored size; the cameras' intrinsics at
        ``size``. ``read=False``: zeros of those shapes, nothing read."""
        if not self.batchable:
            raise ValueError(f"CacheReader: {self} stores Gaussians, not depth")
        width, height = size
        cached = self.cache.image_size(episode)
        w, h = (width, height) if width <= cached[0] and height <= cached[1] else cached
        T, V = len(frames), self.cache.num_views(episode)
        stack = DepthStack(torch.zeros(T, V, h, w, dtype=torch.int16), False,
                           torch.zeros(T, V, 3, 3, dtype=torch.float64), torch.zeros(T, V, 4, 4, dtype=torch.float64))  # fmt: skip
        for k, f in enumerate(frames if read else []):
            (words, stack.coded), cameras = self._read(episode, lambda f=f: self.cache.read_depth_words(episode, f))
            stack.words[k] = words if words.shape[-2:] == (h, w) else nearest_pixels(words, w, h)
            cameras = cameras.resize(width, height)
            stack.K[k], stack.c2w[k] = cameras.K, cameras.c2w
        return stack

    def _ensure(self, episode: int, verify: bool = False) -> None:
        """Build the episode unless the cache holds it (with ``verify``: every checksum passes)."""
        status = self.cache.status(episode)
        if status != "ok" or verify:
            if self.source is None:
                raise FileNotFoundError(
                    f"GenSplatTransform: episode {episode} is {status} in the cache at {self.cache.root} "
                    "and no source was given to build it; run the cache command first"
                )
            if status != "ok":
                logger.warning("GenSplat cache at %s: episode %d is %s; building it in this process (run the "
                               "cache command beforehand to build ahead)", self.cache.root, episode, status)  # fmt: skip
            self.cache.ensure(episode, self.source, verify=verify)

    def _read(self, episode: int, read):
        """``read()`` from the cache; a file whose data fails its checksum is rebuilt once (when
        a source is given) instead of stopping the training run."""
        try:
            return read()
        except CorruptCacheError as e:
            if self.source is None:
                raise
            logger.warning("%s: rebuilding episode %d", e, episode)
            self._ensure(episode, verify=True)
            return read()
