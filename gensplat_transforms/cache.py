"""Per-episode cache of reconstructed Gaussians (safetensors, memory-mapped reads).

One file per episode, ``<root>/episode_<index:06d>.safetensors``, holding every timestep:

* Gaussians are stored quantised: means as uint16 inside the episode's bounding box,
  quaternions as int8, opacities as uint8, scales and SH as float16 (23 bytes per
  Gaussian at SH degree 0 instead of 56).
* The static part of the scene is stored once: pixel-aligned Gaussians whose quantised
  values are identical in every frame of the episode (a fixed camera looking at a static
  table) go into a shared ``static`` group; each frame stores only the rest.
* The header (safetensors metadata) holds the format version, the reconstructor identity
  (name + configuration hash), the dataset fingerprint and a CRC-32 per group. A mismatch
  is reported as :class:`StaleCacheError`; a truncated or corrupted file as
  :class:`CorruptCacheError`. Writes go to a temporary file that is atomically renamed,
  under a lock file so that two workers never build the same episode twice.
"""

from __future__ import annotations

import fcntl
import json
import math
import os
import uuid
import zlib
from collections import OrderedDict
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import torch
from safetensors import safe_open
from safetensors.torch import save_file

from .cameras import Cameras
from .gaussians import Gaussians
from .reconstruction import Reconstruction

FORMAT = "gensplat-cache"
FORMAT_VERSION = 1
_FIELDS = ("means", "quats", "scales", "opacities", "sh")


class CacheError(RuntimeError):
    """Base class of cache problems."""


class StaleCacheError(CacheError):
    """The file was built by another reconstructor, configuration or dataset."""


class CorruptCacheError(CacheError):
    """The file is truncated, unreadable or fails its checksum."""


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


def _crc(tensors: dict[str, torch.Tensor]) -> str:
    c = 0
    for name in sorted(tensors):
        c = zlib.crc32(tensors[name].contiguous().view(torch.uint8).numpy().tobytes(), c)
    return f"{c:08x}"


# ---------------------------------------------------------------------------- the cache


@dataclass
class CacheStats:
    """Sizes of one episode file."""

    num_frames: int
    num_static: int
    bytes: int

    @property
    def bytes_per_timestep(self) -> float:
        return self.bytes / max(self.num_frames, 1)


class GaussianCache:
    """Episode files for one (reconstructor, dataset) pair.

    Args:
        root: folder of the episode files (created on first write).
        reconstructor: identity string of the reconstructor (``Reconstructor.identity()``).
        dataset: fingerprint of the dataset (anything that changes when its content does).
        max_open: episode files kept open (memory-mapped) per process.
    """

    def __init__(self, root: str | Path, reconstructor: str, dataset: str, max_open: int = 8) -> None:
        self.root = Path(root)
        self.reconstructor = reconstructor
        self.dataset = dataset
        self.max_open = max_open
        self._open: OrderedDict[int, _EpisodeFile] = OrderedDict()

    def __getstate__(self) -> dict:  # open file handles do not cross process boundaries
        return {**self.__dict__, "_open": OrderedDict()}

    def path(self, episode: int) -> Path:
        return self.root / f"episode_{int(episode):06d}.safetensors"

    # ------------------------------------------------------------------ writing
    def write_episode(self, episode: int, frames: Sequence[Reconstruction]) -> CacheStats:
        """Quantise and store every frame of an episode (atomic)."""
        if not frames:
            raise ValueError(f"GaussianCache.write_episode: episode {episode} has no frames")
        means = torch.cat([f.gaussians.means.float() for f in frames])
        lo, hi = (means.amin(0), means.amax(0)) if means.numel() else (torch.zeros(3), torch.ones(3))
        qs = [quantize(f.gaussians, lo, hi) for f in frames]
        static = _static_mask(frames, qs)
        tensors: dict[str, torch.Tensor] = {}
        crcs: dict[str, str] = {}
        groups = {"static": {k: v[static[0]] for k, v in qs[0].items()}}
        for t, (f, q) in enumerate(zip(frames, qs)):
            group = {k: v[~static[t]] for k, v in q.items()}
            group["K"] = f.cameras.K.float().clone()
            group["c2w"] = f.cameras.c2w.double().clone()
            groups[f"f{t}"] = group
        for name, group in groups.items():
            crcs[name] = _crc(group)
            tensors.update({f"{name}.{k}": v.contiguous() for k, v in group.items()})
        cam = frames[0].cameras
        meta = {
            "format": FORMAT, "format_version": str(FORMAT_VERSION),
            "reconstructor": self.reconstructor, "dataset": self.dataset,
            "episode_index": str(int(episode)), "num_frames": str(len(frames)),
            "image_size": json.dumps([cam.width, cam.height]),
            "bbox": json.dumps([lo.tolist(), hi.tolist()]), "crc": json.dumps(crcs),
        }  # fmt: skip
        self.root.mkdir(parents=True, exist_ok=True)
        path = self.path(episode)
        tmp = str(self.root / f".{path.name}.{uuid.uuid4().hex}.tmp")
        os.close(os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666))
        mode = os.stat(tmp).st_mode & 0o777  # 0o666 less the umask, as any new file
        try:
            save_file(tensors, tmp, metadata=meta)  # (recreates the file owner-only)
            os.chmod(tmp, mode)
            os.replace(tmp, path)
        finally:
            if os.path.exists(tmp):
                os.unlink(tmp)
        self._open.pop(int(episode), None)
        return CacheStats(len(frames), int(static[0].sum()), path.stat().st_size)

    @contextmanager
    def lock(self, episode: int):
        """Exclusive per-episode lock (a lock file beside the episode file)."""
        self.root.mkdir(parents=True, exist_ok=True)
        with open(self.root / f".episode_{int(episode):06d}.lock", "w") as fh:
            fcntl.flock(fh, fcntl.LOCK_EX)
            try:
                yield
            finally:
                fcntl.flock(fh, fcntl.LOCK_UN)

    def ensure(self, episode: int, build: Callable[[], Sequence[Reconstruction]], verify: bool = False) -> None:
        """Build the episode with ``build()`` unless a valid file exists; stale files and files
        with a bad header are rebuilt, and with ``verify`` also files that fail a checksum
        (reads the whole file). Safe when several processes call it at once."""
        if not verify and self.status(episode) == "ok":
            return
        with self.lock(episode):
            self._open.pop(int(episode), None)  # another process may have replaced the file
            if self.status(episode) != "ok" or (verify and not self.verify(episode)):
                self.write_episode(episode, build())

    def verify(self, episode: int) -> bool:
        """Whether every group of a readable episode file passes its checksum."""
        f = self._file(episode)
        try:
            for name in f.crc:
                f.group(name)
        except CorruptCacheError:
            return False
        return True

    # ------------------------------------------------------------------ reading
    def status(self, episode: int) -> str:
        """'ok', 'missing', 'stale' or 'corrupt' (checks the header, not the checksums)."""
        if not self.path(episode).exists():
            return "missing"
        try:
            self._file(episode)
        except StaleCacheError:
            return "stale"
        except CorruptCacheError:
            return "corrupt"
        return "ok"

    def num_frames(self, episode: int) -> int:
        return self._file(episode).num_frames

    def read(self, episode: int, frame: int) -> Reconstruction:
        """Gaussians (float32) and source cameras of one timestep.

        Raises:
            FileNotFoundError: the episode is not cached.
            StaleCacheError, CorruptCacheError: see the module docstring.
        """
        return self._file(episode).read(frame)

    def _file(self, episode: int) -> _EpisodeFile:
        episode = int(episode)
        if episode in self._open:
            self._open.move_to_end(episode)
            return self._open[episode]
        f = _EpisodeFile(self.path(episode), episode, self.reconstructor, self.dataset)
        self._open[episode] = f
        while len(self._open) > self.max_open:
            self._open.popitem(last=False)
        return f


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
    """An open, validated episode file; decodes frames on demand."""

    def __init__(self, path: Path, episode: int, reconstructor: str, dataset: str) -> None:
        if not path.exists():
            raise FileNotFoundError(f"{path}: episode not cached")
        self.path = path
        try:
            self.handle = safe_open(str(path), framework="pt")
            meta = self.handle.metadata() or {}
        except Exception as e:  # safetensors raises its own error types on bad files
            raise CorruptCacheError(f"{path}: unreadable cache file ({e}); delete it to rebuild") from e
        if meta.get("format") != FORMAT:
            raise CorruptCacheError(f"{path}: not a GenSplat cache file")
        for key, want in (("format_version", str(FORMAT_VERSION)), ("reconstructor", reconstructor),
                          ("dataset", dataset)):  # fmt: skip
            if meta.get(key) != want:
                raise StaleCacheError(f"{path}: built with {key}={meta.get(key)!r}, expected {want!r}")
        if meta.get("episode_index") != str(episode):
            raise CorruptCacheError(f"{path}: holds episode {meta.get('episode_index')}, not {episode}")
        self.num_frames = int(meta["num_frames"])
        self.width, self.height = json.loads(meta["image_size"])
        lo, hi = json.loads(meta["bbox"])
        self.lo, self.hi = torch.tensor(lo), torch.tensor(hi)
        if not (torch.isfinite(self.lo).all() and torch.isfinite(self.hi).all()):
            raise CorruptCacheError(f"{path}: bounding box {meta['bbox']} is not finite; delete it to rebuild")
        self.crc = json.loads(meta["crc"])
        self._static: Gaussians | None = None

    def group(self, name: str) -> dict[str, torch.Tensor]:
        """The tensors of one group (``static`` or ``f<t>``), checksum verified."""
        keys = [k for k in self.handle.keys() if k.startswith(name + ".")]  # noqa: SIM118 (not a dict)
        try:
            group = {k[len(name) + 1 :]: self.handle.get_tensor(k) for k in keys}
        except Exception as e:
            raise CorruptCacheError(f"{self.path}: cannot read group {name!r} ({e})") from e
        if not keys or _crc(group) != self.crc.get(name):
            raise CorruptCacheError(f"{self.path}: checksum mismatch in {name!r}; delete the file to rebuild")
        return group

    def read(self, frame: int) -> Reconstruction:
        if not 0 <= frame < self.num_frames:
            raise IndexError(f"{self.path}: frame {frame} outside 0..{self.num_frames - 1}")
        if self._static is None:  # decoded once per process and episode, then reused
            self._static = dequantize(self.group("static"), self.lo, self.hi)
        group = self.group(f"f{frame}")
        g = Gaussians.cat([self._static, dequantize(group, self.lo, self.hi)])
        cams = Cameras(group["K"], group["c2w"], self.width, self.height)
        return Reconstruction(g, cams)
