"""What the transform reads from a cache, and nothing else.

:class:`CacheReader` answers the two questions a dataset item asks (the Gaussians of its
stacks of frames at their sizes; the stored depth of a stack of frames for the batch path) in
one call each, and owns what reading implies: the item's frame is checked against its
episode and the stacks' frames are clamped to it, an episode that is missing is built from the
source (safe with several workers), and one whose data fails its checksum is rebuilt once. How
the cache stores a timestep (Gaussians, or depth from which Gaussians are rebuilt) stays inside
it: the reader asks the caller for the item's images only when the storage needs them.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

from ..core.scenes import Scenes
from ..core.views import Reconstruction, nearest_pixels
from ..geometry import Reconstructor
from ..geometry.rgbd import RGBDReconstructor
from .depth_codec import depth_from_words
from .store import CorruptCacheError, EpisodeSource, SceneCache

logger = logging.getLogger(__name__)


@dataclass
class DepthStack:
    """The stored depth of T timesteps of V cameras (:meth:`CacheReader.depth`), or of a
    collated batch of them (leading dimensions (S, T)), for :meth:`CacheReader.scenes`.

    Attributes:
        words: (..., T, V, h, w) int16, as the cache stores it (:func:`.depth_codec.depth_from_words`).
        coded: whether the words are log codes (else float16 bits); a bool, or (...) bools.
        K: (..., T, V, 3, 3) float64 intrinsics at the render size; c2w: (..., T, V, 4, 4) float64.
    """

    words: torch.Tensor
    coded: bool | torch.Tensor
    K: torch.Tensor
    c2w: torch.Tensor


class CacheReader:
    """Reads ``cache`` for a transform, building its missing episodes from ``source`` (none:
    a missing episode raises FileNotFoundError) and rebuilding an episode once when its data
    fails a checksum (with a source; without, the CorruptCacheError is raised).

    Example:
        >>> import tempfile
        >>> from gensplat_transforms import RGBDReconstructor
        >>> from gensplat_transforms.cache.builder import SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=3, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> reader = CacheReader(SceneCache(folder.name, RGBDReconstructor(), source.fingerprint), source)
        >>> images = lambda k, offset, frame, size: source.views(0, frame).images
        >>> [stack] = reader.stacks(0, 2, [((-1, 0, 1), (16, 16))], images)  # built on first use
        >>> len(stack), stack[1] is stack[2], len(stack[0].cameras)  # frames 1, 2, 2 (3 clamped): two read
        (3, True, 2)
        >>> reader.depth(0, 2, (-1, 0), (8, 8)).words.shape  # (T, V, h, w)
        torch.Size([2, 2, 8, 8])
        >>> folder.cleanup()
    """

    def __init__(self, cache: SceneCache, source: EpisodeSource | None = None) -> None:
        self.cache = cache
        self.source = source

    def __str__(self) -> str:
        return f"the cache at {self.cache.root} ({self.cache.identity})"

    @property
    def batchable(self) -> bool:
        """Whether :meth:`depth` can serve the batch path: the cache stores depth (from which
        the batch side rebuilds the Gaussians), not Gaussians."""
        return self.cache.kind == "depth"

    def stacks(self, episode: int, frame: int, stacks: Sequence[tuple[Sequence[int], tuple[int, int]]],
               images: Callable[[int, int, int, tuple[int, int]], torch.Tensor]) -> list[tuple[Reconstruction, ...]]:  # fmt: skip
        """The Gaussians and source cameras of each of an item's stacks of frames (one a replaced
        camera): of ``stacks`` = [(offsets, size)], the T timesteps ``frame + offset`` of
        ``episode`` (clamped to it, :func:`_clamped`) at ``size`` = (width, height) (see
        :meth:`.SceneCache.read`), each timestep read once, at the size of the first stack
        that has it. ``images(k, offset, frame, size)`` gives the reconstructed cameras' images of
        the k-th frame of that stack, (V, 3, h, w) float in [0, 1] at ``size``, and is called
        only where the cache rebuilds the Gaussians from them."""
        frames = self._frames(episode, frame)
        read: dict[int, Reconstruction] = {}
        for offsets, size in stacks:
            for k, (o, f) in enumerate(zip(offsets, _clamped(frame, offsets, frames))):
                if f not in read:
                    given = images(k, o, f, size) if self.cache.kind == "depth" else None
                    read[f] = self._read(episode, functools.partial(self.cache.read, episode, f, given, size))
        return [tuple(read[f] for f in _clamped(frame, offsets, frames)) for offsets, _ in stacks]

    def depth(self, episode: int, frame: int, offsets: Sequence[int], size: tuple[int, int],
              read: bool = True) -> DepthStack:  # fmt: skip
        """The stored depth of the T = len(offsets) frames ``frame + offset`` of ``episode``
        (clamped to it) for a render of ``size`` = (width, height): at that size (the stored pixels
        nearest its pixel centres) where it fits in the stored size, else at the stored size; the
        cameras' intrinsics at ``size``. ``read=False``: zeros of those shapes, nothing read (the
        frame is checked all the same)."""
        if not self.batchable:
            raise ValueError(f"CacheReader: {self} stores Gaussians, not depth")
        frames = _clamped(frame, offsets, self._frames(episode, frame))
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

    def scenes(self, stack: DepthStack, images: torch.Tensor, compiled: bool = False) -> Scenes:
        """The scenes of ``stack`` (what :meth:`depth` read, one item's or a collated batch's):
        the Gaussians the cache's reconstructor rebuilds from that depth and the reconstructed
        cameras' ``images`` (..., T, V, 3, h, w) float in [0, 1] at the render size h x w (the
        depth taken at its pixels nearest theirs), one scene per timestep, flattened over the
        leading dimensions (:meth:`.geometry.rgbd.RGBDReconstructor.scenes`; ``compiled``: its
        compiled rule). Raises TypeError for a reconstructor whose Gaussians are not rebuilt
        from depth by the RGB-D disc rule."""
        discs = disc_builder(self.cache.reconstructor)
        h, w = images.shape[-2:]
        words = stack.words if stack.words.shape[-2:] == (h, w) else nearest_pixels(stack.words, w, h)
        coded = stack.coded
        if isinstance(coded, torch.Tensor):  # one per sample: broadcast over its (T, V, h, w)
            coded = coded.to(words.device).reshape(*coded.shape, *(1,) * (words.ndim - coded.ndim))
        depth = depth_from_words(words, coded)
        flat = words.ndim - 3  # leading dimensions into one: (M, V, ...)
        return discs.scenes(*(t.flatten(0, flat - 1) for t in (depth, images, stack.K, stack.c2w)), compiled=compiled)

    def _frames(self, episode: int, frame: int) -> int:
        """The number of frames of ``episode`` (built first if the cache lacks it), which must
        hold ``frame`` (IndexError)."""
        self._ensure(episode)
        frames = self.cache.num_frames(episode)
        if not 0 <= frame < frames:
            raise IndexError(f"GenSplatTransform: frame_index {frame} outside episode {episode} (0..{frames - 1})")
        return frames

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


def _clamped(frame: int, offsets: Sequence[int], frames: int) -> list[int]:
    """The frames ``frame + offset`` clamped to an episode of ``frames`` (a stack reaching past
    it repeats its ends, as LeRobot pads)."""
    return [min(max(frame + o, 0), frames - 1) for o in offsets]


def disc_builder(reconstructor: Reconstructor) -> RGBDReconstructor:
    """The RGB-D disc rule that ``reconstructor`` assembles its cached depth with (the
    ``rgbd`` reconstructor itself, or the ``geometry`` reconstructor's discs); raises for
    reconstructors whose Gaussians are not rebuilt from depth that way (TypeError)."""
    discs = reconstructor if isinstance(reconstructor, RGBDReconstructor) else getattr(reconstructor, "discs", None)
    if not isinstance(discs, RGBDReconstructor):
        raise TypeError(f"render_in='batch' rebuilds RGB-D discs from cached depth; the {reconstructor.name!r} "
                        "reconstructor's cache cannot be rendered that way: use render_in='worker'")  # fmt: skip
    return discs
