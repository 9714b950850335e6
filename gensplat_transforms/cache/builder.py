"""Episode sources (where the views of a timestep come from) and cache building.

An :class:`EpisodeSource` gives, for any (episode, frame), the :class:`Views` of the
cameras to reconstruct. :func:`build_cache` turns a source into a :class:`SceneCache`.
:class:`SceneEpisodes` is the built-in procedural source: the RGB-D tabletop with one
object sliding across the table, rendered exactly.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from collections.abc import Iterable

import torch
from torch.utils.data import Dataset
from tqdm.auto import tqdm

from ..core.cameras import pivot_point
from ..data.scenes import TabletopScene, default_cameras
from ..geometry import Views
from .distributed import Shard
from .store import CacheStats, EpisodeSource, SceneCache

logger = logging.getLogger(__name__)


def build_cache(
    cache: SceneCache, source: EpisodeSource, episodes: Iterable[int], progress: bool = True,
    shard: Shard | None = None, verify: bool = True,
) -> dict[int, CacheStats | None]:
    """Reconstruct and cache every frame of ``episodes`` with the cache's reconstructor.

    Resumable and idempotent: an episode whose file passes every checksum is skipped (its
    value in the result is None); stale, corrupt or half-written ones are rebuilt. With
    ``verify=False`` a file whose header is valid is skipped without reading its data (a
    resume that reads kilobytes per episode instead of the whole cache, or only the file's
    ``stat`` where the cache's index lists it, see :meth:`SceneCache.statuses`): its data checksums
    are still checked on every read, which rebuilds a failing file (transform with a source)
    or raises ``CorruptCacheError``. Several
    processes may run it on the same episodes at once (see :meth:`SceneCache.ensure`).
    With ``shard``, only that shard's share of ``episodes`` is built, longest first (see
    :meth:`~.distributed.Shard.select`); the result holds only those.

    Example:
        >>> import tempfile
        >>> from gensplat_transforms import RGBDReconstructor
        >>> episodes = SceneEpisodes(num_episodes=2, num_frames=3, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = SceneCache(folder.name, RGBDReconstructor(), episodes.fingerprint)
        >>> {e: s.num_frames for e, s in build_cache(cache, episodes, range(2), progress=False).items()}
        {0: 3, 1: 3}
        >>> build_cache(cache, episodes, range(2), progress=False)  # a rerun skips valid episodes
        {0: None, 1: None}
        >>> folder.cleanup()
    """
    episodes = list(episodes) if shard is None else shard.select(episodes, source.num_frames)
    desc = "caching" if shard is None or shard.world == 1 else f"caching (rank {shard.rank}/{shard.world})"
    valid = set() if verify else {e for e, s in cache.statuses(episodes).items() if s == "ok"}
    return {ep: None if ep in valid else cache.ensure(ep, source, verify=verify)
            for ep in tqdm(episodes, desc=desc, unit="episode", disable=not progress)}  # fmt: skip


#: how far (a factor either way) the pivot of two cameras' crossing axes may lie from the
#: scene's depth along camera 0's axis before :func:`pivot_depth` places it at that depth
PIVOT_TOLERANCE = 3.0


def scene_depth(reconstructor, source: EpisodeSource, episodes: Iterable[int], samples: int = 8) -> float:
    """Median depth (metres) along camera 0's optical axis of the Gaussians that
    ``reconstructor`` makes of ``source``: over ``samples`` timesteps (the first and middle
    frames of evenly spaced ``episodes``), the median of each timestep's medians. The pivot
    of a rig of one camera lies there (:func:`.perturbation.rig_pivot`).

    Example:
        >>> from gensplat_transforms import RGBDReconstructor
        >>> source = SceneEpisodes(num_episodes=2, num_frames=3, size=16)
        >>> 0.3 < scene_depth(RGBDReconstructor(), source, range(2)) < 3.0
        True
    """
    return _scene_depth(_timesteps(reconstructor, source, episodes, samples), source)


def pivot_depth(reconstructor, source: EpisodeSource, episodes: Iterable[int], samples: int = 8,
                progress: bool = False) -> float | None:  # fmt: skip
    """The ``GenSplatConfig.pivot_depth`` that ``source`` needs (what ``gensplat cache`` stores).

    One camera: the scene's depth along its axis (:func:`scene_depth`). Two or more: None, the
    pivot where the optical axes of cameras 0 and 1 pass closest
    (:func:`.cameras.pivot_point`), when that point lies in front of both and within a
    factor :data:`PIVOT_TOLERANCE` of the scene's depth along camera 0's axis (medians over the
    sampled timesteps); else (axes nearly parallel, diverging or crossing by the lenses) the
    scene's depth, with a warning: the paper's turns about a pivot metres beyond the scene, or
    behind the cameras, would swing the camera away from what it sees. ``progress`` shows a
    bar over the sampled timesteps' reconstructions.

    Example: the built-in scene's cameras look at the middle of the table
        >>> from gensplat_transforms import RGBDReconstructor
        >>> print(pivot_depth(RGBDReconstructor(), SceneEpisodes(num_episodes=1, num_frames=2, size=16), [0]))
        None
    """
    timesteps = _timesteps(reconstructor, source, episodes, samples, progress)
    if len(source.camera_names) == 1:
        return _scene_depth(timesteps, source)
    c2w = torch.stack([c2w for _, c2w in timesteps])[:, :2]  # (S, 2, 4, 4)
    pivot = pivot_point(c2w[:, 0], c2w[:, 1])  # (S, 3)
    axes = c2w[..., :3, 2] / c2w[..., :3, 2].norm(dim=-1, keepdim=True)
    ahead = ((pivot[:, None] - c2w[..., :3, 3]) * axes).sum(-1).median(0).values  # (2,): along each axis
    medians = [m for m, _ in timesteps if m is not None]
    seen = float(torch.stack(medians).median()) if medians else None  # None: no depth to check against
    if bool((ahead > 0).all()) and (seen is None or seen / PIVOT_TOLERANCE <= float(ahead[0]) <= seen * PIVOT_TOLERANCE):
        return None
    depth = _scene_depth(timesteps, source)  # raises where no depth is seen
    a, b = source.camera_names[:2]
    logger.warning("cameras %r and %r: their optical axes pass closest %.3g m along %r's axis and %.3g m along "
                   "%r's, while the scene lies %.3g m in front of %r (nearly parallel, diverging or crossing "
                   "axes): the pivot is placed on %r's axis at the scene's depth (pivot_depth %.3g)",
                   a, b, float(ahead[0]), a, float(ahead[1]), b, depth, a, a, depth)  # fmt: skip
    return depth


def _timesteps(reconstructor, source: EpisodeSource, episodes: Iterable[int], samples: int, progress: bool = False
               ) -> list[tuple[torch.Tensor | None, torch.Tensor]]:  # fmt: skip
    """Per sampled timestep (the first and middle frames of up to ``samples // 2`` evenly spaced
    ``episodes``): the median depth along camera 0's axis of the opaque Gaussians in front of
    it (None where there are none) and the rig's (V, 4, 4) camera-to-world poses."""
    episodes = list(episodes)
    chosen = [episodes[round(i * (len(episodes) - 1) / max(samples // 2 - 1, 1))]
              for i in range(min(len(episodes), max(samples // 2, 1)))]  # fmt: skip
    picked = [(ep, frame) for ep in dict.fromkeys(chosen) for frame in dict.fromkeys((0, source.num_frames(ep) // 2))]
    out = []
    for ep, frame in tqdm(picked, desc="placing the pivot", unit="timestep", disable=not progress):
        rec = reconstructor.reconstruct(source.views(ep, frame))
        c2w = rec.cameras.c2w
        axis = c2w[0, :3, 2] / c2w[0, :3, 2].norm()
        z = (rec.gaussians.means.to(c2w) - c2w[0, :3, 3]) @ axis
        z = z[(z > 0) & (rec.gaussians.opacities.to(c2w) > 0.5)]
        out.append((z.median() if len(z) else None, c2w))
    return out


def _scene_depth(timesteps: list[tuple[torch.Tensor | None, torch.Tensor]], source: EpisodeSource) -> float:
    """The median of the timesteps' median depths (:func:`_timesteps`)."""
    medians = [m for m, _ in timesteps if m is not None]
    if not medians:
        raise ValueError(f"no reconstructed point in front of camera {source.camera_names[0]!r} in {len(timesteps)} "
                         "sampled timesteps: the pivot cannot be placed at the scene's depth")  # fmt: skip
    return float(torch.stack(medians).median())


class SceneEpisodes:
    """Procedural RGB-D episodes: episode e is ``TabletopScene(seed + e)`` with its first
    object sliding ``step_m`` per frame along world x, seen by the default cameras.

    Cameras are named ``left``, ``right`` (external, reconstructed) and ``front``.
    """

    camera_names = ("left", "right")

    def __init__(self, num_episodes: int = 2, num_frames: int = 8, size: int = 64, seed: int = 0,
                 step_m: float = 0.01) -> None:
        self.num_episodes, self.frames, self.size, self.seed, self.step_m = (
            num_episodes, num_frames, size, seed, step_m)  # fmt: skip
        self.cameras = default_cameras(size, size)
        self.fingerprint = hashlib.sha256(
            repr(("scene-episodes", num_episodes, num_frames, size, seed, step_m)).encode()
        ).hexdigest()[:16]

    def num_frames(self, episode: int) -> int:
        return self.frames

    def scene(self, episode: int, frame: int) -> TabletopScene:
        base = TabletopScene(self.seed + episode)
        first = base.objects[0]
        x, y, z = first.center
        moved = dataclasses.replace(first, center=(x + self.step_m * frame, y, z))
        return base.with_objects((moved, *base.objects[1:]))

    def render(self, episode: int, frame: int) -> tuple[torch.Tensor, torch.Tensor]:
        """All three cameras: rgb (3, 3, H, W), depth (3, 1, H, W)."""
        return self.scene(episode, frame).render(self.cameras)

    def views(self, episode: int, frame: int) -> Views:
        rgb, depth = self.render(episode, frame)
        return Views(rgb[:2], self.cameras[:2], depth[:2])


class SceneDataset(Dataset):
    """A LeRobot-style map dataset over :class:`SceneEpisodes` (images pre-rendered).

    Items: ``observation.images.<left|right|front>`` (3, H, W) float in [0, 1],
    ``episode_index``, ``frame_index`` and ``index`` (int64 scalars).
    """

    names = ("left", "right", "front")

    def __init__(self, episodes: SceneEpisodes) -> None:
        self.episodes = episodes
        self.index = [(e, f) for e in range(episodes.num_episodes) for f in range(episodes.frames)]
        self.images = {ef: episodes.render(*ef)[0] for ef in self.index}

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> dict:
        e, f = self.index[i]
        item = {f"observation.images.{n}": self.images[(e, f)][k] for k, n in enumerate(self.names)}
        return {**item, "episode_index": torch.tensor(e), "frame_index": torch.tensor(f), "index": torch.tensor(i)}
