"""Per-episode cache of what a reconstructor computed (safetensors, positioned reads).

One file per episode, ``<root>/episode_<index:06d>.safetensors``, holding every timestep.
What it stores depends on the reconstructor:

* ``depth`` (any :class:`~.geometry.DepthReconstructor`, e.g. RGB-D): only what the
  worker cannot recompute cheaply: each view's depth, compressed with a bounded error
  (:mod:`.depth_codec`: 16-bit log codes, the static scene once, Zstandard), and the cameras. The
  worker rebuilds the Gaussians from the item's own images with
  ``reconstructor.assemble`` (a few milliseconds per timestep). About 10-20 kB per
  timestep for two 224x224 views.
  Where the reconstructor only cleans depth the dataset already carries (RGB-D sensor
  depth, ``DepthReconstructor.given_depth``) and the source names that depth's files
  (``depth_files``), nothing of it is stored: the episode file *links* the dataset's depth
  files (paths relative to the cache folder, their sizes and CRC-32s) and holds the cameras
  once, about 1 kB per episode; workers read each frame's depth from the dataset, frame
  by frame. ``link_depth=False`` stores the compressed copy instead (e.g. where the dataset
  sits on slow network storage: 4-17 kB per timestep to read instead of the raw depth).
* ``gaussians`` (any other reconstructor, e.g. the feed-forward model's Gaussian head):
  the Gaussians themselves, quantised (means as uint16 inside the episode's bounding box,
  quaternions int8, opacities uint8, scales and SH float16: 23 bytes per Gaussian at SH
  degree 0); pixel-aligned Gaussians identical in every frame are stored once.

Trust: the header (safetensors metadata) names the format version, the kind, the
reconstructor identity and the dataset fingerprint; a mismatch is :class:`StaleCacheError`.
Every tensor has a CRC-32 over its name, dtype, shape and bytes, and the header has a CRC-32
over all its other fields, so no edit of a label or a field goes unnoticed: a file that is
truncated, edited or fails a checksum is :class:`CorruptCacheError`. A linked depth file that
is missing, has another size or shape than when it was linked makes the episode stale (the
dataset changed); full verification also compares its CRC-32. Writes go to a
temporary file (``.episode_<index>.safetensors.tmp``) that is atomically renamed, under a
per-episode lock, so concurrent builders never build one episode twice; a builder killed
mid-write leaves a temporary file that the next builder of that episode removes.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
from collections import OrderedDict
from collections.abc import Iterable
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import torch
from safetensors.torch import save

from ..core.atomic import atomic_write, read_json_object, replaceable, stat_stamp
from ..core.cameras import Cameras
from ..core.renamed import renamed
from ..geometry import DepthReconstructor, Reconstruction, Reconstructor, Views
from .format import (
    FORMAT,
    FORMAT_VERSION,
    CacheError,
    CorruptCacheError,
    DepthFiles,
    EpisodeFile,
    ReplacedError,
    StaleCacheError,
    check_sidecars,
    dequantize,
    encode_depth,
    encode_gaussians,
    encode_links,
    file_crc,
    header_crc,
    quantize,
    tensor_crc,
)

__all__ = ["CacheError", "CacheStats", "CorruptCacheError", "DepthFiles", "EpisodeSource", "SceneCache",
           "StaleCacheError", "dequantize", "quantize", "size_text"]  # fmt: skip

logger = logging.getLogger(__name__)

class EpisodeSource(Protocol):
    """Views of the reconstructed cameras, per timestep (see :mod:`.episodes`).

    Attributes:
        camera_names: names of the cameras ``views`` returns, in order.
        fingerprint: changes whenever the content changes (keys the cache).

    A source whose depth lives in files may also define ``depth_files(episode) ->
    DepthFiles | None``; a depth cache then links them instead of copying the depth. A source
    that reads a whole episode faster than frame by frame may define ``episode_views(episode)
    -> Iterator[Views]`` (every frame's ``views``, in order); a build then uses it.
    """

    camera_names: tuple[str, ...]
    fingerprint: str

    def num_frames(self, episode: int) -> int: ...

    def views(self, episode: int, frame: int) -> Views: ...


def size_text(num_bytes: float) -> str:
    """``num_bytes`` for people: "17 B", "4.2 kB", "88.0 MB"."""
    for unit, scale in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if num_bytes >= scale:
            return f"{num_bytes / scale:.1f} {unit}"
    return f"{num_bytes:.0f} B"


@dataclass
class CacheStats:
    """Sizes of one episode file."""

    num_frames: int
    bytes: int

    @property
    def bytes_per_timestep(self) -> float:
        return self.bytes / max(self.num_frames, 1)


#: episode files a process keeps parsed (their headers: a read opens the file, nothing stays open) ...
MAX_KEPT = 1024
#: ... and the memory their decoded parts (cameras, depth references, static Gaussians) may take
KEEP_BYTES = 64 << 20
#: the files found valid, with their stat (see :meth:`SceneCache.statuses`)
INDEX_NAME = "index.json"


class SceneCache:
    """What every timestep of a dataset needs to render, one file per episode, for one
    (reconstructor, dataset) pair: the reconstructor's Gaussians, or (a ``depth`` cache) the
    depth and cameras from which workers rebuild its RGB-D discs. Formerly ``GaussianCache``.

    Args:
        root: folder of the episode files (created on first write).
        reconstructor: what builds the episodes; its :meth:`~.Reconstructor.identity` keys
            the files, and a :class:`~.geometry.DepthReconstructor` makes this a
            ``depth`` cache (see the module docstring).
        dataset: fingerprint of the dataset (anything that changes when its content does).
        keep_bytes: memory a process may spend on the episode files it keeps parsed (their
            cameras, decoded depth references and static Gaussians, least recently read
            dropped first; at most ``MAX_KEPT`` files), so that a worker sampling at random
            reopens as few as it can: about 1.3 MB per stored 2x640x480 episode, 0.3 MB at
            2x224x224, a few kB for one that links the dataset's depth.
        link_depth: link the dataset's own depth files instead of storing a copy, where the
            reconstructor only cleans given depth and the source names the files (see the
            module docstring); False stores the copy, and makes linked episodes stale.

    Example: cache the procedural RGB-D episodes (a ``depth`` cache)
        >>> import tempfile
        >>> from gensplat_transforms import RGBDReconstructor
        >>> from gensplat_transforms.cache.builder import SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=2, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = SceneCache(folder.name, RGBDReconstructor(), source.fingerprint)
        >>> cache.ensure(0, source).num_frames, cache.status(0)
        (2, 'ok')
        >>> result = cache.read(0, 1, source.views(0, 1).images)  # Gaussians rebuilt from the images
        >>> folder.cleanup()
    """

    def __init__(self, root: str | Path, reconstructor: Reconstructor, dataset: str, keep_bytes: int = KEEP_BYTES,
                 link_depth: bool = True) -> None:
        if not isinstance(reconstructor, Reconstructor):
            raise TypeError(f"SceneCache: expected a Reconstructor, got {type(reconstructor).__name__}")
        self.root = Path(root)
        self.reconstructor = reconstructor
        self.identity = reconstructor.identity()
        self.kind = "depth" if isinstance(reconstructor, DepthReconstructor) else "gaussians"
        self.dataset = dataset
        self.keep_bytes = keep_bytes
        self.link_depth = link_depth and getattr(reconstructor, "given_depth", False)
        self._kept: OrderedDict[int, EpisodeFile] = OrderedDict()  # parsed, least recently read first
        self._kept_bytes = 0  # their nbytes

    def __getstate__(self) -> dict:  # each process parses the files it reads
        return {**self.__dict__, "_kept": OrderedDict(), "_kept_bytes": 0}

    def _forget(self, episode: int) -> None:
        """Drop the parsed file of ``episode`` (it is being rebuilt or was replaced)."""
        f = self._kept.pop(int(episode), None)
        self._kept_bytes -= f.nbytes if f is not None else 0

    def path(self, episode: int) -> Path:
        return self.root / f"episode_{int(episode):06d}.safetensors"

    # ------------------------------------------------------------------ building
    def ensure(self, episode: int, source: EpisodeSource, verify: bool = False) -> CacheStats | None:
        """Build ``episode`` from ``source`` unless a valid file exists; returns the new file's
        stats, or None when it was already valid. Stale and corrupt files are rebuilt; with
        ``verify`` every checksum is read first (else only the header's). Safe when several
        processes or machines sharing the folder call it at once: the first builds, the
        others wait and find it valid."""
        if not verify and self.status(episode) == "ok":
            return None
        with self.lock(episode):
            self._forget(episode)  # another process may have replaced the file
            found = _stat_key(self.path(episode)) or []  # [] when missing
            if self.status(episode) == "ok" and (not verify or self.verify(episode)):
                return None
            return self._build(episode, source, found)

    def _build(self, episode: int, source: EpisodeSource, found: list[int] | None = None) -> CacheStats | None:
        """Reconstruct and write one episode (the caller holds its lock); None when the episode
        file's :func:`_stat_key` is not ``found`` any more (given: [] for none), as another builder
        replaced it since."""
        replaceable(self.path(episode))
        if source.fingerprint != self.dataset:
            raise StaleCacheError(
                f"{self.root}: the source's fingerprint {source.fingerprint!r} is not this cache's {self.dataset!r}"
            )
        n = source.num_frames(episode)
        if n < 1:
            raise ValueError(f"SceneCache: episode {episode} has no frames")
        rec = self.reconstructor
        depth_files = getattr(source, "depth_files", None) if getattr(rec, "given_depth", False) else None
        given = depth_files(episode) if depth_files is not None else None
        if given is not None:  # linked or copied: the files must be this episode's, of these cameras
            check_sidecars(given, episode, n)
        links = given if self.link_depth else None
        tmp = self._tmp(episode)
        while True:  # normally once: lock() removed or waited for any earlier temporary file
            try:
                fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)  # the umask applies
            except FileExistsError:
                _remove_or_wait(tmp)
                continue
            fcntl.flock(fd, fcntl.LOCK_EX)  # tells later builders this file is being written
            if _stat_key(tmp) == stat_stamp(os.fstat(fd)):
                break
            os.close(fd)  # removed as a dead builder's before it was locked
        try:  # the temporary file, created and locked, is what excludes other builders for sure
            if found is not None and (_stat_key(self.path(episode)) or []) != found:
                return None  # built meanwhile by a builder that a deleted lock file let in
            if links is not None:
                tensors, meta = encode_links(links, n, self.root)
            else:
                every_view = getattr(source, "episode_views", None)
                views = every_view(episode) if every_view else (source.views(episode, t) for t in range(n))
                # a depth episode is encoded frame by frame as they come (a model batches a few timesteps)
                frames = rec.predict_depths(views) if self.kind == "depth" else (rec(v) for v in views)
                tensors, meta = encode_depth(frames, n) if self.kind == "depth" else encode_gaussians(list(frames))
            meta.update(format=FORMAT, format_version=FORMAT_VERSION, kind=self.kind, reconstructor=self.identity,
                        dataset=self.dataset, episode_index=str(int(episode)), num_frames=str(n))  # fmt: skip
            meta["crc"] = json.dumps({k: tensor_crc(k, v) for k, v in tensors.items()}, sort_keys=True)
            meta["header_crc"] = header_crc(meta)
            data = save(tensors, metadata=meta)
            with os.fdopen(os.dup(fd), "wb") as fh:
                fh.write(data)
                fh.flush()
                os.fsync(fh.fileno())
            os.replace(tmp, self.path(episode))
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
            os.close(fd)
        self._forget(episode)
        return CacheStats(n, len(data))

    def _tmp(self, episode: int) -> Path:
        """The one temporary file a builder of ``episode`` writes (named without listing the folder)."""
        return self.root / f".{self.path(episode).name}.tmp"

    @contextmanager
    def lock(self, episode: int):
        """Exclusive per-episode lock (``.episode_<index>.lock`` beside the file).

        Robust to the lock file being deleted: a lock taken on a file that is no longer at its
        path is retried, and temporary files still locked by a builder whose lock file was
        removed are waited for; unlocked ones (a builder was killed) are removed. Two builders
        let in by a deleted lock file build once: the temporary file is created exclusively
        before a build, and a builder that finds the episode file replaced since it looked
        does not build (see :meth:`ensure`). A symbolic link where the lock file goes is
        refused with ``ValueError``."""
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.root / f".episode_{int(episode):06d}.lock"
        if path.is_symlink():  # opening it would create its target, wherever it points (the dataset)
            raise ValueError(f"{path} is a symbolic link where GenSplat keeps a lock file: remove it")
        while True:
            fd = os.open(path, os.O_CREAT | os.O_RDWR, 0o666)
            fcntl.flock(fd, fcntl.LOCK_EX)
            try:
                if os.fstat(fd).st_ino == os.stat(path).st_ino:
                    break
            except FileNotFoundError:
                pass
            os.close(fd)
        try:
            _remove_or_wait(self._tmp(episode))
            yield
        finally:
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    # ------------------------------------------------------------------ reading
    def status(self, episode: int) -> str:
        """'ok', 'missing', 'stale' or 'corrupt' (checks the whole header, not the data)."""
        if not self.path(episode).exists():
            return "missing"
        try:
            self._file(episode)
        except StaleCacheError:
            return "stale"
        except CorruptCacheError:
            return "corrupt"
        except FileNotFoundError:
            return "missing"
        return "ok"

    def statuses(self, episodes: Iterable[int]) -> dict[int, str]:
        """:meth:`status` of many episodes, without opening the files checked before.

        Every file found "ok" is listed in ``<root>/index.json`` with its size, modification
        time and inode, under the format version, reconstructor identity, dataset fingerprint
        and depth linking it was checked for; a listed file whose ``stat`` still matches is
        "ok" without being opened (one ``stat`` instead of a header read: what makes checking
        a cache of many thousands of episodes before training take a second). Every other
        episode is checked by :meth:`status`, and the index rewritten atomically when it
        changed. An index that is unreadable or made for other settings is ignored (and
        replaced); a folder that cannot be written to only loses the speed-up. Linked depth
        files are not looked at for a listed episode: their changes are the dataset
        fingerprint's to show (a LeRobot dataset's covers them); opening the episode to read
        it still checks their sizes. Data checksums are checked on every read, as always."""
        index_path, identity = self.root / INDEX_NAME, self._index_identity()
        index = read_json_object(index_path)
        known = index.get("files") if index.get("for") == identity else None
        known = known if isinstance(known, dict) else {}
        listed, found = dict(known), {}
        for episode in episodes:
            episode, name = int(episode), self.path(episode).name
            key = _stat_key(self.path(episode))  # before the header is read: a file replaced
            if key is not None and known.get(name) == key:  # meanwhile is checked again next time
                found[episode] = "ok"
                continue
            found[episode] = self.status(episode)
            listed.pop(name, None)
            if found[episode] == "ok" and key is not None:
                listed[name] = key
        if listed != known and self.root.is_dir():
            try:
                text = json.dumps({"for": identity, "files": listed}, separators=(",", ":"))
                atomic_write(index_path, lambda tmp: Path(tmp).write_text(text))
            except (OSError, ValueError) as e:  # a read-only folder, a folder in the way
                logger.info("SceneCache: cannot write %s (%s): the next check opens every file again", index_path, e)
        return found

    def _index_identity(self) -> dict[str, str | bool]:
        return {"format_version": FORMAT_VERSION, "reconstructor": self.identity, "dataset": self.dataset,
                "link_depth": self.link_depth}  # fmt: skip

    def verify(self, episode: int) -> bool:
        """Whether every tensor of a readable episode file passes its checksum, and every
        depth file it links has the CRC-32 it had when linked."""
        def check(f: EpisodeFile) -> bool:
            for name in f.crc:
                f.tensor(name)
            return all(file_crc(path) == crc for path, _, crc in f.links)

        try:
            return self._reading(episode, check)
        except (CacheError, OSError):
            return False

    def num_frames(self, episode: int) -> int:
        return self._file(episode).num_frames

    def image_size(self, episode: int) -> tuple[int, int]:
        """(width, height) of the cached cameras."""
        f = self._file(episode)
        return f.width, f.height

    def num_views(self, episode: int) -> int:
        """The number of cameras each timestep of ``episode`` holds."""
        return self._file(episode).num_views

    def read(self, episode: int, frame: int, images: torch.Tensor | None = None,
             size: tuple[int, int] | None = None) -> Reconstruction:  # fmt: skip
        """Gaussians (float32) and source cameras of one timestep.

        Args:
            images: (V, 3, h, w) float in [0, 1], the reconstructed cameras' images of this
                timestep at ``size``; required by a ``depth`` cache, which builds the
                Gaussians from them, ignored otherwise.
            size: (width, height) to build at, default the cached size: the cameras'
                intrinsics are scaled to it and a depth cache takes the depth at the pixel
                nearest each pixel centre of that size (:func:`.geometry.base.nearest_pixels`).
        Raises:
            FileNotFoundError: the episode is not cached.
            IndexError: ``frame`` is outside the episode.
            StaleCacheError, CorruptCacheError: see the module docstring.
        """
        if self.kind == "gaussians":
            found, (width, height) = self._reading(episode, lambda f: (f.gaussians(frame), (f.width, f.height)))
            resized = size not in (None, (width, height))
            return Reconstruction(found.gaussians, found.cameras.resize(*size)) if resized else found
        if images is None:
            raise ValueError(f"SceneCache.read: a depth cache ({self.identity}) needs the views' images")
        return self.reconstructor.assemble(self._reading(episode, lambda f: f.depth_views(frame, images, size)))

    def read_depth(self, episode: int, frame: int) -> tuple[torch.Tensor, Cameras]:
        """The stored depth (V, 1, H, W) float32 and cameras of one timestep of a ``depth``
        cache (what :meth:`read` builds the Gaussians from). Raises as :meth:`read`."""
        return self._reading(episode, lambda f: (f.depth(frame), f.cameras(frame)), depth=True)

    def read_depth_words(self, episode: int, frame: int) -> tuple[tuple[torch.Tensor, bool], Cameras]:
        """The depth of one timestep as stored, ((V, H, W) int16 words, whether they are log
        codes), uncleaned (:func:`.depth_codec.depth_from_words` decodes them), and its cameras:
        half the bytes of :meth:`read_depth`'s float32, for a process that decodes elsewhere."""
        return self._reading(episode, lambda f: (f.depth_words(frame), f.cameras(frame)), depth=True)

    def _reading(self, episode: int, read, depth: bool = False):
        """``read(parsed file of episode)``; a file replaced or removed since this process
        parsed it (rebuilt by another) is parsed again, once. ``depth``: a depth cache's read."""
        if depth and self.kind != "depth":
            raise ValueError(f"SceneCache: {self.identity} stores Gaussians, not depth")
        try:
            return self._counted(self._file(episode), read)
        except ReplacedError:
            self._forget(episode)
            return self._counted(self._file(episode), read)

    def _counted(self, f: EpisodeFile, read):
        """``read(f)``, counting what it decoded into ``f`` against the budget."""
        held = f.nbytes
        try:
            return read(f)
        finally:
            self._count(f, f.nbytes - held)

    def _file(self, episode: int) -> EpisodeFile:
        episode = int(episode)
        f = self._kept.get(episode)
        if f is not None:
            self._kept.move_to_end(episode)
            return f
        f = self._kept[episode] = EpisodeFile(self.path(episode), episode, self)
        self._count(f, f.nbytes)
        return f

    def _count(self, f: EpisodeFile, nbytes: int) -> None:
        """Count ``nbytes`` more held by ``f`` (if kept) and drop the least recently read
        files beyond the budget, never the most recent."""
        if self._kept.get(f.episode) is f:
            self._kept_bytes += nbytes
        while len(self._kept) > 1 and (len(self._kept) > MAX_KEPT or self._kept_bytes > self.keep_bytes):
            self._kept_bytes -= self._kept.popitem(last=False)[1].nbytes


def _stat_key(path: Path) -> list[int] | None:
    """:func:`.atomic.stat_stamp` of a file, None if absent."""
    try:
        return stat_stamp(path.stat())
    except OSError:
        return None


def _remove_or_wait(tmp: Path) -> None:
    """Remove a builder's temporary file if no live process holds it, else wait for it."""
    try:
        fd = os.open(tmp, os.O_RDONLY)
    except FileNotFoundError:
        return
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:  # a live builder: wait until it has renamed or dropped the file
            fcntl.flock(fd, fcntl.LOCK_EX)
            return
        if os.path.exists(tmp) and os.stat(tmp).st_ino == os.fstat(fd).st_ino:
            os.unlink(tmp)
    finally:
        os.close(fd)

__getattr__ = renamed(__name__)  # the former GaussianCache
