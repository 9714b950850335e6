"""Per-episode cache of what a reconstructor computed (safetensors, positioned reads).

One file per episode, ``<root>/episode_<index:06d>.safetensors``, holding every timestep.
What it stores depends on the reconstructor:

* ``depth`` (any :class:`~.reconstruction.DepthReconstructor`, e.g. RGB-D): only what the
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
import math
import os
import zlib
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
from safetensors.torch import save

from . import depth_codec
from .atomic import atomic_write, read_json_object, stat_stamp
from .cameras import Cameras
from .dataset_format import open_depth
from .gaussians import Gaussians
from .reconstruction import DepthReconstructor, Reconstruction, Reconstructor, Views
from .reconstruction.base import nearest_pixels
from .tensor_file import FileChangedError, TensorFile

logger = logging.getLogger(__name__)

FORMAT = "gensplat-cache"
FORMAT_VERSION = "2"
_FIELDS = ("means", "quats", "scales", "opacities", "sh")
#: dtype of every stored tensor, by the last part of its name (frame digits dropped)
_DTYPES = {"means": torch.uint16, "quats": torch.int8, "scales": torch.float16, "opacities": torch.uint8,
           "sh": torch.float16, "K": torch.float64, "c2w": torch.float64, "reference": torch.uint8, "f": torch.uint8}  # fmt: skip


class CacheError(RuntimeError):
    """Base class of cache problems."""


class StaleCacheError(CacheError):
    """The file was built by another format, reconstructor, configuration or dataset."""


class CorruptCacheError(CacheError):
    """The file is truncated, unreadable, malformed or fails a checksum."""


class _ReplacedError(CorruptCacheError):
    """The file was replaced or removed since this process parsed it (a rebuild): the cache
    parses it again once, so this only escapes when it is replaced again meanwhile."""


@dataclass(frozen=True)
class DepthFiles:
    """The depth a dataset carries for one episode: one file per reconstructed camera, in the
    depth format of :mod:`.dataset_format` (tensor ``"depth"`` (T, H, W), metres, 0 = invalid),
    the V cameras it was taken with and their names (each file's own metadata must name the
    same camera, episode and frame count)."""

    paths: tuple[Path, ...]
    cameras: Cameras
    names: tuple[str, ...] = ()


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


# ---------------------------------------------------------------------------- quantisation


def quantize(g: Gaussians, lo: torch.Tensor, hi: torch.Tensor) -> dict[str, torch.Tensor]:
    """Compact storage of Gaussians whose means lie in the box [lo, hi] (each (3,))."""
    span = (hi - lo).clamp_min(1e-9)
    q = g.quats.float()
    q = q / q.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    q = q * torch.where(q[:, :1] < 0, -1.0, 1.0)
    return {
        "means": ((g.means.float() - lo) / span * 65535).round().clamp(0, 65535).to(torch.int32).to(torch.uint16),
        "quats": (q * 127).round().to(torch.int8),
        "scales": g.scales.float().clamp(max=6e4).to(torch.float16),
        "opacities": (g.opacities.float() * 255).round().to(torch.uint8),
        "sh": g.sh.float().clamp(-6e4, 6e4).to(torch.float16),
    }


def dequantize(d: dict[str, torch.Tensor], lo: torch.Tensor, hi: torch.Tensor) -> Gaussians:
    """Inverse of :func:`quantize` (float32). Valid by construction for finite ``lo``, ``hi``
    and checksummed input (``quantize`` clamps), so the result is marked checked."""
    span = (hi - lo).clamp_min(1e-9)
    return Gaussians(
        means=d["means"].to(torch.int32).float() / 65535 * span + lo,
        quats=d["quats"].float() / 127,
        scales=d["scales"].float(),
        opacities=d["opacities"].float() / 255,
        sh=d["sh"].float(),
        validate=False,
    ).mark_checked()


def _row_bytes(d: dict[str, torch.Tensor]) -> torch.Tensor:
    """(N, B) uint8: every Gaussian's quantised fields as one byte row (N may be 0)."""
    n = d["means"].shape[0]
    width = [math.prod(d[k].shape[1:]) * d[k].element_size() for k in _FIELDS]
    return torch.cat([d[k].contiguous().view(torch.uint8).reshape(n, w) for k, w in zip(_FIELDS, width)], 1)


def _tensor_crc(name: str, t: torch.Tensor) -> str:
    """CRC-32 of a tensor's name, dtype, shape and bytes."""
    head = f"{name}\0{t.dtype}\0{tuple(t.shape)}\0".encode()
    return f"{zlib.crc32(t.contiguous().view(torch.uint8).numpy(), zlib.crc32(head)):08x}"


def _header_crc(meta: dict[str, str]) -> str:
    body = {k: v for k, v in meta.items() if k != "header_crc"}
    return f"{zlib.crc32(json.dumps(body, sort_keys=True).encode()):08x}"


def _file_crc(path: Path, chunk: int = 1 << 22) -> str:
    """CRC-32 of a file's bytes."""
    crc = 0
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def _blob(data: bytes) -> torch.Tensor:
    return torch.frombuffer(bytearray(data), dtype=torch.uint8)


# ---------------------------------------------------------------------------- the cache


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
#: the files found valid, with their stat (see :meth:`GaussianCache.statuses`)
INDEX_NAME = "index.json"


class GaussianCache:
    """Episode files for one (reconstructor, dataset) pair.

    Args:
        root: folder of the episode files (created on first write).
        reconstructor: what builds the episodes; its :meth:`~.Reconstructor.identity` keys
            the files, and a :class:`~.reconstruction.DepthReconstructor` makes this a
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
        >>> from gensplat_transforms.episodes import SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=2, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = GaussianCache(folder.name, RGBDReconstructor(), source.fingerprint)
        >>> cache.ensure(0, source).num_frames, cache.status(0)
        (2, 'ok')
        >>> result = cache.read(0, 1, source.views(0, 1).images)  # Gaussians rebuilt from the images
        >>> folder.cleanup()
    """

    def __init__(self, root: str | Path, reconstructor: Reconstructor, dataset: str, keep_bytes: int = KEEP_BYTES,
                 link_depth: bool = True) -> None:
        if not isinstance(reconstructor, Reconstructor):
            raise TypeError(f"GaussianCache: expected a Reconstructor, got {type(reconstructor).__name__}")
        self.root = Path(root)
        self.reconstructor = reconstructor
        self.identity = reconstructor.identity()
        self.kind = "depth" if isinstance(reconstructor, DepthReconstructor) else "gaussians"
        self.dataset = dataset
        self.keep_bytes = keep_bytes
        self.link_depth = link_depth and getattr(reconstructor, "given_depth", False)
        self._kept: OrderedDict[int, _EpisodeFile] = OrderedDict()  # parsed, least recently read first
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
        if source.fingerprint != self.dataset:
            raise StaleCacheError(
                f"{self.root}: the source's fingerprint {source.fingerprint!r} is not this cache's {self.dataset!r}"
            )
        n = source.num_frames(episode)
        if n < 1:
            raise ValueError(f"GaussianCache: episode {episode} has no frames")
        rec = self.reconstructor
        depth_files = getattr(source, "depth_files", None) if getattr(rec, "given_depth", False) else None
        given = depth_files(episode) if depth_files is not None else None
        if given is not None:  # linked or copied: the files must be this episode's, of these cameras
            _check_sidecars(given, episode, n)
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
                tensors, meta = _encode_links(links, n, self.root)
            else:
                every_view = getattr(source, "episode_views", None)
                views = every_view(episode) if every_view else (source.views(episode, t) for t in range(n))
                # a depth episode is encoded frame by frame as they come (a model batches a few timesteps)
                frames = rec.predict_depths(views) if self.kind == "depth" else (rec(v) for v in views)
                tensors, meta = _encode_depth(frames, n) if self.kind == "depth" else _encode_gaussians(list(frames))
            meta.update(format=FORMAT, format_version=FORMAT_VERSION, kind=self.kind, reconstructor=self.identity,
                        dataset=self.dataset, episode_index=str(int(episode)), num_frames=str(n))  # fmt: skip
            meta["crc"] = json.dumps({k: _tensor_crc(k, v) for k, v in tensors.items()}, sort_keys=True)
            meta["header_crc"] = _header_crc(meta)
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
        does not build (see :meth:`ensure`)."""
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.root / f".episode_{int(episode):06d}.lock"
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
            except OSError as e:
                logger.info("GaussianCache: cannot write %s (%s): the next check opens every file again", index_path, e)
        return found

    def _index_identity(self) -> dict[str, str | bool]:
        return {"format_version": FORMAT_VERSION, "reconstructor": self.identity, "dataset": self.dataset,
                "link_depth": self.link_depth}  # fmt: skip

    def verify(self, episode: int) -> bool:
        """Whether every tensor of a readable episode file passes its checksum, and every
        depth file it links has the CRC-32 it had when linked."""
        def check(f: _EpisodeFile) -> bool:
            for name in f.crc:
                f.tensor(name)
            return all(_file_crc(path) == crc for path, _, crc in f.links)

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
                nearest each pixel centre of that size (:func:`.reconstruction.base.nearest_pixels`).
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
            raise ValueError(f"GaussianCache.read: a depth cache ({self.identity}) needs the views' images")
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
            raise ValueError(f"GaussianCache: {self.identity} stores Gaussians, not depth")
        try:
            return self._counted(self._file(episode), read)
        except _ReplacedError:
            self._forget(episode)
            return self._counted(self._file(episode), read)

    def _counted(self, f: _EpisodeFile, read):
        """``read(f)``, counting what it decoded into ``f`` against the budget."""
        held = f.nbytes
        try:
            return read(f)
        finally:
            self._count(f, f.nbytes - held)

    def _file(self, episode: int) -> _EpisodeFile:
        episode = int(episode)
        f = self._kept.get(episode)
        if f is not None:
            self._kept.move_to_end(episode)
            return f
        f = self._kept[episode] = _EpisodeFile(self.path(episode), episode, self)
        self._count(f, f.nbytes)
        return f

    def _count(self, f: _EpisodeFile, nbytes: int) -> None:
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


# ---------------------------------------------------------------------------- encodings


def _cameras(cameras: Sequence[Cameras]) -> dict[str, torch.Tensor]:
    return {"K": torch.stack([c.K.double() for c in cameras]).contiguous(),
            "c2w": torch.stack([c.c2w.double() for c in cameras]).contiguous()}  # fmt: skip


def _encode_depth(frames: Iterable[Views], num_frames: int) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and header fields of a depth episode of ``num_frames`` frames from
    ``predict_depth``, consumed one at a time: only their quantised depth (2 bytes a pixel)
    is held until the episode's reference is known, never their images (see
    :func:`.depth_codec.encode_episode`)."""
    cameras = []

    def depths():
        for f in frames:  # Views match their depth maps to their images, not to their cameras
            (h, w), cam = f.depths.shape[-2:], f.cameras
            if (h, w) != (cam.height, cam.width):
                raise ValueError(f"GaussianCache: depth maps are {w}x{h}, the cameras {cam.width}x{cam.height}")
            cameras.append(cam)
            yield f.depths[:, 0]  # (V, H, W)

    ref, blobs = depth_codec.encode_episode(depths(), num_frames)
    tensors = {"depth.reference": _blob(ref), **{f"depth.f{t}": _blob(b) for t, b in enumerate(blobs)}}
    cam = cameras[0]
    meta = {"image_size": json.dumps([cam.width, cam.height]), "num_views": str(len(cam)),
            "depth_codec": json.dumps({"step": depth_codec.STEP, "d_min": depth_codec.D_MIN, "d_max": depth_codec.D_MAX,
                                       "compression": depth_codec.COMPRESSION})}  # fmt: skip
    return {**tensors, **_cameras(cameras)}, meta


def _check_sidecars(files: DepthFiles, episode: int, num_frames: int) -> None:
    """ValueError naming the file when a depth file's own metadata names another camera,
    episode or frame count than it is read as (e.g. another camera's file copied over it)."""
    for path, name in zip(map(Path, files.paths), files.names or [None] * len(files.paths)):
        try:
            meta = TensorFile(path).metadata
        except (OSError, ValueError) as e:
            raise ValueError(f"unreadable depth file: {e}") from e
        want = {"camera": name, "episode_index": str(int(episode)), "num_frames": str(num_frames)}
        wrong = [(k, meta[k], v) for k, v in want.items() if v is not None and k in meta and meta[k] != v]
        if wrong:
            says = ", ".join(f"{k.replace('_index', '')} {got!r}" for k, got, _ in wrong)
            expected = ", ".join(f"{k.replace('_index', '')} {v!r}" for k, _, v in wrong)
            raise ValueError(f"{path}: this depth file says {says}, expected {expected} (copied or renamed from "
                             "elsewhere?); import the camera's depth again (gensplat import-depth --overwrite)")


def _encode_links(files: DepthFiles, num_frames: int, root: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors (the cameras, once) and header fields of a depth episode that links the
    dataset's depth files (paths relative to the cache folder ``root``)."""
    cam = files.cameras
    if len(files.paths) != len(cam):
        raise ValueError(f"GaussianCache: {len(files.paths)} depth files for {len(cam)} cameras")
    links = []
    for path in map(Path, files.paths):
        shape = tuple(open_depth(path).get_shape())
        if shape != (num_frames, cam.height, cam.width):
            raise ValueError(f"GaussianCache: {path} holds depth of shape {shape}, expected "
                             f"({num_frames}, {cam.height}, {cam.width}): {num_frames} frames at the cameras' size")  # fmt: skip
        links.append({"path": os.path.relpath(path, root), "bytes": path.stat().st_size, "crc": _file_crc(path)})
    meta = {"image_size": json.dumps([cam.width, cam.height]), "num_views": str(len(cam)),
            "depth_links": json.dumps(links)}  # fmt: skip
    return {"K": cam.K.double()[None].contiguous(), "c2w": cam.c2w.double()[None].contiguous()}, meta


def _encode_gaussians(frames: Sequence[Reconstruction]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and header fields of a Gaussians episode."""
    means = torch.cat([f.gaussians.means.float() for f in frames])
    lo, hi = (means.amin(0), means.amax(0)) if means.numel() else (torch.zeros(3), torch.ones(3))
    qs = [quantize(f.gaussians, lo, hi) for f in frames]
    static = _static_mask(frames, qs)
    tensors = {f"static.{k}": v[static[0]].contiguous() for k, v in qs[0].items()}
    for t, q in enumerate(qs):
        tensors.update({f"f{t}.{k}": v[~static[t]].contiguous() for k, v in q.items()})
    cam = frames[0].cameras
    meta = {"image_size": json.dumps([cam.width, cam.height]), "num_views": str(len(cam)),
            "bbox": json.dumps([lo.tolist(), hi.tolist()])}  # fmt: skip
    return {**tensors, **_cameras([f.cameras for f in frames])}, meta


def _static_mask(frames: Sequence[Reconstruction], qs: list[dict]) -> list[torch.Tensor]:
    """Per frame, (N_t,) bool: this Gaussian is the only one at its pixel in every frame and
    bit-identical there in every frame."""
    false = [torch.zeros(len(f.gaussians), dtype=torch.bool) for f in frames]
    if len(frames) < 2 or any(f.pixel_ids is None for f in frames):
        return false
    npix = max(int(f.pixel_ids.max()) + 1 if len(f.pixel_ids) else 0 for f in frames)
    rows = [_row_bytes(q) for q in qs]
    ref = torch.zeros(npix, rows[0].shape[1], dtype=torch.uint8)
    same = torch.zeros(npix, dtype=torch.bool)
    ref[frames[0].pixel_ids] = rows[0]
    same[frames[0].pixel_ids] = True
    for f, r in zip(frames, rows):
        here = torch.zeros(npix, dtype=torch.bool)
        here[f.pixel_ids] = (r == ref[f.pixel_ids]).all(1)
        same &= here & (torch.bincount(f.pixel_ids, minlength=npix) == 1)  # a shared pixel is never static
    return [same[f.pixel_ids] for f in frames]


class _EpisodeFile:
    """An open episode file whose whole header was validated; decodes frames on demand.
    ``nbytes``: the memory it holds (cameras, header, the parts it decoded so far)."""

    def __init__(self, path: Path, episode: int, cache: GaussianCache) -> None:
        if not path.exists():
            raise FileNotFoundError(f"{path}: episode not cached")
        self.path, self.episode = path, episode
        try:
            self._file = TensorFile(path)
        except FileNotFoundError:
            raise FileNotFoundError(f"{path}: episode not cached") from None
        except (OSError, ValueError) as e:
            raise CorruptCacheError(f"{path}: unreadable cache file ({e}); it is rebuilt on the next build") from e
        meta = self._file.metadata
        if meta.get("format") != FORMAT:
            raise CorruptCacheError(f"{path}: not a GenSplat cache file")
        if meta.get("format_version") != FORMAT_VERSION:
            raise StaleCacheError(f"{path}: cache format {meta.get('format_version')!r}, expected {FORMAT_VERSION!r}")
        if meta.get("header_crc") != _header_crc(meta):
            raise CorruptCacheError(f"{path}: header checksum mismatch (the header was edited or damaged)")
        for key, want in (("kind", cache.kind), ("reconstructor", cache.identity), ("dataset", cache.dataset)):
            if meta.get(key) != want:
                raise StaleCacheError(f"{path}: built with {key}={meta.get(key)!r}, expected {want!r}")
        if "depth_links" in meta and not cache.link_depth:
            raise StaleCacheError(f"{path}: links the dataset's depth files; this cache stores copies (link_depth=False)")
        try:
            self._parse(meta, episode)
        except (KeyError, ValueError, TypeError) as e:
            raise CorruptCacheError(f"{path}: malformed header ({type(e).__name__}: {e})") from e
        self._linked = [self._open_link(p, size) for p, size, _ in self.links]
        self._clean = cache.reconstructor.clean_depth if self.links else None
        self._static: Gaussians | None = None
        self._reference: np.ndarray | None = None  # depth_codec.reference_rows
        self.nbytes = self.K.nbytes + self.c2w.nbytes + self._file.header_bytes

    def _parse(self, meta: dict[str, str], episode: int) -> None:
        if int(meta["episode_index"]) != episode:
            raise ValueError(f"holds episode {meta['episode_index']}, not {episode}")
        self.num_frames, self.num_views = int(meta["num_frames"]), int(meta["num_views"])
        self.width, self.height = (int(x) for x in json.loads(meta["image_size"]))
        if min(self.num_frames, self.num_views, self.width, self.height) < 1:
            raise ValueError("num_frames, num_views and image_size must be positive")
        self.crc = dict(json.loads(meta["crc"]))
        if set(self.crc) != set(self._file.keys()):
            raise ValueError("the checksum list and the stored tensors differ")
        for name in self.crc:
            dtype, want = self._file.dtype(name), _DTYPES[name.rsplit(".", 1)[-1].rstrip("0123456789")]
            if dtype != want:
                raise ValueError(f"tensor {name!r} is labelled {dtype}, expected {want}")
        if meta["kind"] == "gaussians":
            lo, hi = json.loads(meta["bbox"])
            self.lo, self.hi = torch.tensor(lo, dtype=torch.float32), torch.tensor(hi, dtype=torch.float32)
            if self.lo.shape != (3,) or self.hi.shape != (3,) or not torch.isfinite(torch.cat([self.lo, self.hi])).all():
                raise ValueError(f"bounding box {meta['bbox']} is not two finite 3-vectors")
        #: (path, bytes, crc) of each linked depth file, in view order; empty when the depth is stored.
        #: The relative path is joined lexically, as it was made: <root>/gensplat may link to another disk
        self.links = [(Path(os.path.normpath(self.path.parent / d["path"])), int(d["bytes"]), str(d["crc"]))
                      for d in json.loads(meta.get("depth_links", "[]"))]  # fmt: skip
        if self.links and len(self.links) != self.num_views:
            raise ValueError(f"{len(self.links)} linked depth files for {self.num_views} views")
        #: how the stored depth's blobs are compressed (files that do not say: zlib)
        self.compression = json.loads(meta.get("depth_codec", "{}")).get("compression", "zlib")
        if self.compression not in depth_codec.COMPRESSIONS:
            raise ValueError(f"depth compression {self.compression!r}, known: {depth_codec.COMPRESSIONS}")
        self.K, self.c2w = self.tensor("K"), self.tensor("c2w")
        want = (1 if self.links else self.num_frames, self.num_views)  # linked: the cameras once
        if self.K.shape != (*want, 3, 3) or self.c2w.shape != (*want, 4, 4) or self.K.dtype != torch.float64:
            raise ValueError(f"cameras of shape {tuple(self.K.shape)} / {tuple(self.c2w.shape)}, expected {want} views")

    def _open_link(self, path: Path, size: int):
        """A linked depth file (read frame by frame), after checking it is the file that was linked
        (as far as its size and shape tell; its CRC is checked by ``verify``)."""
        try:
            now = path.stat().st_size
        except FileNotFoundError:
            raise StaleCacheError(f"{self.path}: the dataset's depth file {path} it links is gone") from None
        if now != size:
            raise StaleCacheError(f"{self.path}: the dataset's depth file {path} changed since it was linked "
                                  f"({size} -> {now} bytes)")  # fmt: skip
        try:
            depth = open_depth(path)
        except ValueError as e:
            raise StaleCacheError(f"{self.path}: {e}") from e
        if tuple(depth.get_shape()) != (self.num_frames, self.height, self.width):
            raise StaleCacheError(f"{self.path}: the dataset's depth file {path} holds depth of shape "
                                  f"{tuple(depth.get_shape())}, linked as {(self.num_frames, self.height, self.width)}")  # fmt: skip
        return depth

    def tensor(self, name: str) -> torch.Tensor:
        """One stored tensor, checksum verified."""
        try:
            t = self._file.read(name)
        except (FileChangedError, FileNotFoundError) as e:
            raise _ReplacedError(f"{self.path}: replaced or removed since it was opened ({e})") from e
        except (OSError, ValueError) as e:
            raise CorruptCacheError(f"{self.path}: cannot read {name!r} ({e})") from e
        if _tensor_crc(name, t) != self.crc.get(name):
            raise CorruptCacheError(f"{self.path}: checksum mismatch in {name!r}; it is rebuilt on the next build")
        return t

    def _check_frame(self, frame: int) -> None:
        if not 0 <= frame < self.num_frames:
            raise IndexError(f"{self.path}: frame {frame} outside 0..{self.num_frames - 1}")

    def cameras(self, frame: int) -> Cameras:
        t = 0 if self.links else frame  # linked: the cameras once
        return Cameras(self.K[t], self.c2w[t], self.width, self.height)

    def depth_views(self, frame: int, images: torch.Tensor, size: tuple[int, int] | None = None) -> Views:
        """Views of one frame at ``size`` (width, height; default the cached size): the given
        images, the cached cameras and depth (a linked file's uncleaned: ``assemble`` cleans
        it), see :meth:`GaussianCache.read`."""
        width, height = size or (self.width, self.height)
        want = (self.num_views, 3, height, width)
        if tuple(images.shape) != want:
            raise ValueError(f"GaussianCache.read: images of shape {tuple(images.shape)}, expected {want}")
        depth, cameras = self.depth(frame, clean=False), self.cameras(frame)
        if (width, height) != (self.width, self.height):
            depth, cameras = nearest_pixels(depth, width, height), cameras.resize(width, height)
        return Views(images, cameras, depth)

    def depth(self, frame: int, clean: bool = True) -> torch.Tensor:
        """(V, 1, H, W) float32 depth of one frame; a linked file's is the dataset's, cleaned
        as the reconstructor cleans it unless ``clean`` is False (stored depth is clean)."""
        words, coded = self.depth_words(frame)
        depth = depth_codec.depth_from_words(words, coded)[:, None]
        return self._clean(depth) if clean and not coded else depth

    def depth_words(self, frame: int) -> tuple[torch.Tensor, bool]:
        """(V, H, W) int16: one frame's depth as stored, two bytes a pixel, and whether they
        are log codes (stored depth) rather than float16 bits (a linked file's); see
        :func:`.depth_codec.depth_from_words`."""
        self._check_frame(frame)
        if self._linked:
            try:
                return self._linked_words(frame), False
            except FileChangedError:  # rewritten since opened: read on if its size and shape still match
                self._linked = [self._open_link(p, size) for p, size, _ in self.links]
                return self._linked_words(frame), False
        if self._reference is None:  # decompressed once per process and episode, then reused
            blob = self.tensor("depth.reference").numpy()
            try:
                shape = (self.num_views, self.height, self.width)
                self._reference = depth_codec.reference_rows(blob, shape, self.compression)
            except ValueError as e:
                raise CorruptCacheError(f"{self.path}: undecodable depth reference ({e})") from e
            self.nbytes += self._reference.nbytes
        blob = self.tensor(f"depth.f{frame}").numpy()
        try:
            codes = depth_codec.decode_codes(self._reference, blob, self.compression)
        except ValueError as e:
            raise CorruptCacheError(f"{self.path}: undecodable depth of frame {frame} ({e})") from e
        return torch.from_numpy(codes.view(np.int16)), True

    def _linked_words(self, frame: int) -> torch.Tensor:
        try:
            return torch.cat([d[frame : frame + 1] for d in self._linked]).view(torch.int16)
        except FileChangedError:
            raise
        except (OSError, ValueError) as e:  # removed since the episode was opened
            raise StaleCacheError(f"{self.path}: the dataset's depth file it links changed ({e})") from e

    def gaussians(self, frame: int) -> Reconstruction:
        self._check_frame(frame)
        if self._static is None:
            self._static = dequantize(self._group("static"), self.lo, self.hi)
            self.nbytes += sum(t.nbytes for t in self._static.tensors().values())
        g = Gaussians.cat([self._static, dequantize(self._group(f"f{frame}"), self.lo, self.hi)])
        return Reconstruction(g, self.cameras(frame))

    def _group(self, name: str) -> dict[str, torch.Tensor]:
        return {k: self.tensor(f"{name}.{k}") for k in _FIELDS}
