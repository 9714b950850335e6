"""The cache's files: what one episode file holds and how it is written and read back.

The layout (see :mod:`.cache` for what each kind stores and why): a safetensors file whose
header names the format version, the kind, the reconstructor identity and the dataset
fingerprint, with a CRC-32 per tensor (over its name, dtype, shape and bytes) and one over the
header's other fields. ``encode_*`` turn an episode into tensors and header fields;
:class:`EpisodeFile` opens one, validates its whole header and decodes frames on demand.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from ..core.cameras import Cameras
from ..core.gaussians import Gaussians
from ..core.tensor_file import FileChangedError, TensorFile
from ..data.format import open_depth
from ..geometry import Reconstruction, Reconstructor, Views
from ..geometry.base import nearest_pixels
from . import depth_codec

FORMAT = "gensplat-cache"
FORMAT_VERSION = "2"
FIELDS = ("means", "quats", "scales", "opacities", "sh")
#: dtype of every stored tensor, by the last part of its name (frame digits dropped)
DTYPES = {"means": torch.uint16, "quats": torch.int8, "scales": torch.float16, "opacities": torch.uint8,
           "sh": torch.float16, "K": torch.float64, "c2w": torch.float64, "reference": torch.uint8, "f": torch.uint8}  # fmt: skip




class CacheError(RuntimeError):
    """Base class of cache problems."""


class StaleCacheError(CacheError):
    """The file was built by another format, reconstructor, configuration or dataset."""


class CorruptCacheError(CacheError):
    """The file is truncated, unreadable, malformed or fails a checksum."""


class ReplacedError(CorruptCacheError):
    """The file was replaced or removed since this process parsed it (a rebuild): the cache
    parses it again once, so this only escapes when it is replaced again meanwhile."""


@dataclass(frozen=True)
class DepthFiles:
    """The depth a dataset carries for one episode: one file per reconstructed camera, in the
    depth format of :mod:`.data.format` (tensor ``"depth"`` (T, H, W), metres, 0 = invalid),
    the V cameras it was taken with and their names (each file's own metadata must name the
    same camera, episode and frame count)."""

    paths: tuple[Path, ...]
    cameras: Cameras
    names: tuple[str, ...] = ()


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
    width = [math.prod(d[k].shape[1:]) * d[k].element_size() for k in FIELDS]
    return torch.cat([d[k].contiguous().view(torch.uint8).reshape(n, w) for k, w in zip(FIELDS, width)], 1)


def tensor_crc(name: str, t: torch.Tensor) -> str:
    """CRC-32 of a tensor's name, dtype, shape and bytes."""
    head = f"{name}\0{t.dtype}\0{tuple(t.shape)}\0".encode()
    return f"{zlib.crc32(t.contiguous().view(torch.uint8).numpy(), zlib.crc32(head)):08x}"


def header_crc(meta: dict[str, str]) -> str:
    body = {k: v for k, v in meta.items() if k != "header_crc"}
    return f"{zlib.crc32(json.dumps(body, sort_keys=True).encode()):08x}"


def file_crc(path: Path, chunk: int = 1 << 22) -> str:
    """CRC-32 of a file's bytes."""
    crc = 0
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            crc = zlib.crc32(block, crc)
    return f"{crc:08x}"


def _blob(data: bytes) -> torch.Tensor:
    return torch.frombuffer(bytearray(data), dtype=torch.uint8)


# ---------------------------------------------------------------------------- encodings


def _cameras(cameras: Sequence[Cameras]) -> dict[str, torch.Tensor]:
    return {"K": torch.stack([c.K.double() for c in cameras]).contiguous(),
            "c2w": torch.stack([c.c2w.double() for c in cameras]).contiguous()}  # fmt: skip


def encode_depth(frames: Iterable[Views], num_frames: int) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors and header fields of a depth episode of ``num_frames`` frames from
    ``predict_depth``, consumed one at a time: only their quantised depth (2 bytes a pixel)
    is held until the episode's reference is known, never their images (see
    :func:`.depth_codec.encode_episode`)."""
    cameras = []

    def depths():
        for f in frames:  # Views match their depth maps to their images, not to their cameras
            (h, w), cam = f.depths.shape[-2:], f.cameras
            if (h, w) != (cam.height, cam.width):
                raise ValueError(f"SceneCache: depth maps are {w}x{h}, the cameras {cam.width}x{cam.height}")
            cameras.append(cam)
            yield f.depths[:, 0]  # (V, H, W)

    ref, blobs = depth_codec.encode_episode(depths(), num_frames)
    tensors = {"depth.reference": _blob(ref), **{f"depth.f{t}": _blob(b) for t, b in enumerate(blobs)}}
    cam = cameras[0]
    meta = {"image_size": json.dumps([cam.width, cam.height]), "num_views": str(len(cam)),
            "depth_codec": json.dumps({"step": depth_codec.STEP, "d_min": depth_codec.D_MIN, "d_max": depth_codec.D_MAX,
                                       "compression": depth_codec.COMPRESSION})}  # fmt: skip
    return {**tensors, **_cameras(cameras)}, meta


def check_sidecars(files: DepthFiles, episode: int, num_frames: int) -> None:
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


def encode_links(files: DepthFiles, num_frames: int, root: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """Tensors (the cameras, once) and header fields of a depth episode that links the
    dataset's depth files (paths relative to the cache folder ``root``)."""
    cam = files.cameras
    if len(files.paths) != len(cam):
        raise ValueError(f"SceneCache: {len(files.paths)} depth files for {len(cam)} cameras")
    links = []
    for path in map(Path, files.paths):
        shape = tuple(open_depth(path).get_shape())
        if shape != (num_frames, cam.height, cam.width):
            raise ValueError(f"SceneCache: {path} holds depth of shape {shape}, expected "
                             f"({num_frames}, {cam.height}, {cam.width}): {num_frames} frames at the cameras' size")  # fmt: skip
        links.append({"path": os.path.relpath(path, root), "bytes": path.stat().st_size, "crc": file_crc(path)})
    meta = {"image_size": json.dumps([cam.width, cam.height]), "num_views": str(len(cam)),
            "depth_links": json.dumps(links)}  # fmt: skip
    return {"K": cam.K.double()[None].contiguous(), "c2w": cam.c2w.double()[None].contiguous()}, meta


def encode_gaussians(frames: Sequence[Reconstruction]) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
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


class CacheIdentity(Protocol):
    """What an episode file is checked against (a :class:`.cache.SceneCache`): its kind
    ("depth" or "gaussians"), reconstructor identity and dataset fingerprint, whether it links
    the dataset's depth, and the reconstructor whose ``clean_depth`` cleans linked depth."""

    kind: str
    identity: str
    dataset: str
    link_depth: bool
    reconstructor: Reconstructor


class EpisodeFile:
    """An open episode file whose whole header was validated; decodes frames on demand.
    ``nbytes``: the memory it holds (cameras, header, the parts it decoded so far)."""

    def __init__(self, path: Path, episode: int, cache: CacheIdentity) -> None:
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
        if meta.get("header_crc") != header_crc(meta):
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
            dtype, want = self._file.dtype(name), DTYPES[name.rsplit(".", 1)[-1].rstrip("0123456789")]
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
            raise ReplacedError(f"{self.path}: replaced or removed since it was opened ({e})") from e
        except (OSError, ValueError) as e:
            raise CorruptCacheError(f"{self.path}: cannot read {name!r} ({e})") from e
        if tensor_crc(name, t) != self.crc.get(name):
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
        it), see :meth:`SceneCache.read`."""
        width, height = size or (self.width, self.height)
        want = (self.num_views, 3, height, width)
        if tuple(images.shape) != want:
            raise ValueError(f"SceneCache.read: images of shape {tuple(images.shape)}, expected {want}")
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
        return {k: self.tensor(f"{name}.{k}") for k in FIELDS}
