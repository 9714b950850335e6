"""Bounded-error, lossless-after-quantisation compression of an episode's depth maps.

Depth d (metres) is quantised on a log scale, ``k = round(log(d / D_MIN) / STEP) + 1`` as
uint16, so the relative error is at most ``exp(STEP / 2) - 1`` = 2.4e-4 (float16's own
precision) at every distance from ``D_MIN`` = 1 um to ``D_MAX`` = 1000 km (smaller positive
depths are stored as ``D_MIN``); code 0 marks "no depth" (0, negative, non-finite or beyond
``D_MAX``, as for the reconstructors). A pixel's error in the novel view is then a small
fraction of a pixel at any distance, where a linear step would waste bits near the camera
and lose them far away.

An episode is coded as its per-pixel median code (the static scene, stored once) plus, per
frame, the difference to it (zero wherever nothing moved), each made a row-wise difference
(smooth surfaces give small numbers) and compressed with Zstandard with its content checksum
(``COMPRESSION``, ``"zstd+checksum"``: XXH64 of the decompressed bytes, checked on decode, about
free): a damaged blob raises rather than decode to other depth. Blobs written before the checksum
(``"zstd"``) or with zlib, the earlier choice (``"zlib"``), still decode, unchecked. All arithmetic
is modulo 2^16, so decoding is exact. Every frame decodes on its own from the median and its
blob (Zstandard level 6: faster than zlib at about the same size; docs/cache.md).
"""

from __future__ import annotations

import functools
import math
import zlib
from collections.abc import Iterable

import numpy as np
import torch
import zstandard

D_MIN = 1e-6
D_MAX = 1e6
STEP = 2.0**-11
MAX_RELATIVE_ERROR = math.expm1(STEP / 2)
#: how new blobs are compressed; ``COMPRESSIONS`` are those that decode
COMPRESSION = "zstd+checksum"
COMPRESSIONS = ("zstd+checksum", "zstd", "zlib")
_LEVEL = 6
_MEDIAN_BLOCK = 16384  # pixels per block of the reference's median (see encode_episode)


def quantize_depth(depth: torch.Tensor) -> np.ndarray:
    """(..., H, W) depth in metres -> uint16 codes of the same shape (0 = no depth)."""
    d = depth.detach().cpu().double().numpy()
    ok = (d > 0) & (d <= D_MAX)  # NaN fails both
    k = np.rint(np.log(np.where(ok, np.maximum(d, D_MIN), D_MIN) / D_MIN) / STEP) + 1
    return np.where(ok, k, 0).astype(np.uint16)


def dequantize_depth(codes: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`quantize_depth`: float32 metres, 0 where the code is 0 (on the
    device of a tensor; int16 tensors are read as uint16). A lookup in the table of all
    2^16 codes' metres (:func:`_metres`): at 2x640x480 about 13x faster than the exponential."""
    if isinstance(codes, torch.Tensor) and codes.device.type != "cpu":
        return _metres(codes.device)[codes.long() & 0xFFFF]
    k = codes.numpy() if isinstance(codes, torch.Tensor) else np.asarray(codes)
    k = k.view(np.uint16) if k.dtype in (np.int16, np.uint16) else k.astype(np.int64) & 0xFFFF
    return torch.from_numpy(np.take(_metres(torch.device("cpu")).numpy(), k))


@functools.cache
def _metres(device: torch.device) -> torch.Tensor:
    """(65536,) float32 metres of every code on ``device`` (0 for code 0), computed in float64."""
    k = torch.arange(2**16, dtype=torch.float64)
    return torch.where(k > 0, D_MIN * torch.exp((k - 1) * STEP), 0.0).float().to(device)


def depth_from_words(words: torch.Tensor, coded: torch.Tensor | bool) -> torch.Tensor:
    """float32 metres from (...) int16 depth words, two bytes a pixel as a cache stores them:
    log codes where ``coded`` (broadcastable; :func:`quantize_depth`), else the bits of float16
    metres (a dataset's linked depth files)."""
    if words.dtype != torch.int16:
        raise ValueError(f"depth_from_words: expected int16 words, got {words.dtype}")
    if isinstance(coded, bool):  # one coding: decode only that way
        return dequantize_depth(words) if coded else words.view(torch.float16).float()
    coded = torch.as_tensor(coded, device=words.device)
    return torch.where(coded, dequantize_depth(words), words.view(torch.float16).float())


def _pack(codes: np.ndarray) -> bytes:
    rows = np.diff(codes, axis=-1, prepend=np.uint16(0)).tobytes()
    return zstandard.ZstdCompressor(level=_LEVEL, write_checksum=True).compress(rows)


def reference_rows(blob: bytes, shape: tuple[int, ...], compression: str = COMPRESSION) -> np.ndarray:
    """An episode's reference as stored: (V, H, W) uint16 differences along each row of its
    codes, what :func:`decode_codes` takes (one decompression; raises ValueError for a blob
    that does not decode to ``shape`` or fails its checksum)."""
    size = 2 * math.prod(shape)
    if compression not in COMPRESSIONS:
        raise ValueError(f"unknown depth compression {compression!r}; known: {COMPRESSIONS}")
    try:
        if compression == "zlib":
            data = zlib.decompress(blob)
        else:  # a checksum the frame holds is checked by the decoder; "zstd+checksum" must hold one
            if compression == "zstd+checksum" and not zstandard.get_frame_parameters(blob).has_checksum:
                raise ValueError("depth blob without its checksum (damaged)")
            data = zstandard.ZstdDecompressor().decompress(blob, max_output_size=size)
    except (zlib.error, zstandard.ZstdError) as e:
        raise ValueError(f"undecodable depth blob ({type(e).__name__}: {e})") from e
    if len(data) != size:
        raise ValueError(f"depth blob holds {len(data) // 2} values, expected {math.prod(shape)}")
    return np.frombuffer(data, dtype=np.uint16).reshape(shape)


def _row_sums(differences: np.ndarray) -> np.ndarray:
    """Codes from their row differences, modulo 2^16 (PyTorch's int16 prefix sum: about 3x
    numpy's uint16 one at 2x640x480, and two's complement wraps alike)."""
    return torch.from_numpy(differences.view(np.int16)).cumsum(-1, dtype=torch.int16).numpy().view(np.uint16)


def encode_episode(depths: torch.Tensor | Iterable[torch.Tensor], num_frames: int | None = None
                   ) -> tuple[bytes, list[bytes]]:  # fmt: skip
    """(T, V, H, W) depth of an episode (one tensor, or T tensors of (V, H, W)) -> (reference
    blob, one blob per frame), compressed with ``COMPRESSION``. ``num_frames``: T, for an
    iterator (else ``len(depths)``).

    Frames are quantised as they come into one array of codes allocated up front (2 bytes a
    pixel: an iterator's float frames are never held together, and no frame's temporaries
    are left between two frames' codes to fragment the heap), and the median taken over
    blocks of pixels, each block's codes made contiguous per pixel first: the float64
    temporaries and the median's reads stay in the CPU caches (docs/cache.md)."""
    if num_frames is None and not hasattr(depths, "__len__"):
        raise TypeError("encode_episode: an iterator of frames needs num_frames")
    total = len(depths) if num_frames is None else num_frames
    if total < 1:
        raise ValueError(f"encode_episode: an episode of {total} frames")
    codes, count = None, 0
    for d in depths:
        if count == total:
            raise ValueError(f"encode_episode: more than the {total} frames announced")
        c = quantize_depth(d)
        if codes is None:
            codes = np.empty((total, *c.shape), np.uint16)
        codes[count] = c
        count += 1
    if count != total:
        raise ValueError(f"encode_episode: {count} frames, {total} announced")
    flat, ref = codes.reshape(total, -1), np.empty(codes[0].size, np.uint16)
    for i in range(0, flat.shape[1], _MEDIAN_BLOCK):
        ref[i : i + _MEDIAN_BLOCK] = np.median(np.ascontiguousarray(flat[:, i : i + _MEDIAN_BLOCK].T), axis=-1)
    ref = ref.reshape(codes.shape[1:])  # the median rounded down, as astype(uint16) rounds
    return _pack(ref), [_pack(c - ref) for c in codes]  # uint16 arithmetic wraps modulo 2^16


def decode_reference(blob: bytes, shape: tuple[int, ...], compression: str = COMPRESSION) -> np.ndarray:
    """The (V, H, W) uint16 reference codes of an episode; raises ValueError for a bad blob."""
    return _row_sums(reference_rows(blob, shape, compression).copy())  # writable for PyTorch


def decode_codes(reference: np.ndarray, blob: bytes, compression: str = COMPRESSION) -> np.ndarray:
    """(V, H, W) uint16 codes of one frame from its episode's :func:`reference_rows` and its
    blob: the two row differences added, then summed along each row once (the frame's codes
    are the reference's plus its differences, and sums commute modulo 2^16)."""
    rows = reference_rows(blob, reference.shape, compression)
    return _row_sums(np.add(rows, reference))


def decode_frame(reference: np.ndarray, blob: bytes, compression: str = COMPRESSION) -> torch.Tensor:
    """(V, 1, H, W) float32 depth of one frame from :func:`reference_rows` and its blob."""
    return dequantize_depth(decode_codes(reference, blob, compression))[:, None]
