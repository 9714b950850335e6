"""A safetensors file read with positioned reads: no memory map, no file handle kept.

A training worker reads one frame of an episode file at random, most often of a file it has
not read for a while. Mapping a file and unmapping it later costs more than the read itself
(page faults on first touch, a TLB shootdown when unmapped), and an open handle per kept file
runs into the process's file limit; so the header is parsed and checked once, and every read
opens the file, checks that it is still the file that was parsed (inode, size, modification
time), and reads the bytes it needs (``os.preadv``).
"""

from __future__ import annotations

import json
import math
import os
import struct
from pathlib import Path

import torch

from .atomic import stat_stamp

#: safetensors dtype names this library reads, with their PyTorch dtypes
DTYPES = {"F64": torch.float64, "F32": torch.float32, "F16": torch.float16, "BF16": torch.bfloat16,
          "I64": torch.int64, "I32": torch.int32, "I16": torch.int16, "I8": torch.int8,
          "U16": torch.uint16, "U8": torch.uint8, "BOOL": torch.bool}  # fmt: skip
MAX_HEADER_BYTES = 100 << 20  # safetensors' own limit


class FileChangedError(ValueError):
    """The file was replaced, cut or edited since its header was parsed."""


class TensorFile:
    """The tensors of one safetensors file, read on demand.

    Attributes:
        path: the file.
        metadata: its ``__metadata__`` (str -> str; empty if it has none).
        header_bytes: length of its JSON header.

    Raises ``ValueError`` naming the file when it is not a safetensors file whose tensors' data
    ends where the file does, and ``OSError`` when it cannot be read. Each tensor's entry is
    checked when first used (a known dtype, its shape's size, inside the data): a reader of
    one frame does not pay for checking hundreds.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        with open(self.path, "rb") as f:
            self._stamp = stat_stamp(os.fstat(f.fileno()))
            size = self._stamp[0]
            head = f.read(8)
            if len(head) != 8:
                raise ValueError(f"{self.path}: not a safetensors file ({size} bytes)")
            (n,) = struct.unpack("<Q", head)
            if not 2 <= n <= min(size - 8, MAX_HEADER_BYTES):
                raise ValueError(f"{self.path}: not a safetensors file (header length {n} in a file of {size} bytes)")
            raw = f.read(n)
        try:
            header = json.loads(raw)
        except (ValueError, UnicodeDecodeError) as e:
            raise ValueError(f"{self.path}: unreadable safetensors header ({e})") from e
        if not isinstance(header, dict):
            raise ValueError(f"{self.path}: the safetensors header is not a JSON object")  # noqa: TRY004 (the file's content)
        self.header_bytes, self._data, self._data_size = n, 8 + n, size - 8 - n
        metadata = header.pop("__metadata__", None) or {}
        if not isinstance(metadata, dict) or not all(isinstance(v, str) for v in metadata.values()):
            raise ValueError(f"{self.path}: metadata that is not str -> str")
        self.metadata: dict[str, str] = metadata
        try:  # (dtype name, shape, first, end byte) per tensor: tuples the garbage collector skips
            self._header = {name: (e["dtype"], tuple(e["shape"]), *e["data_offsets"]) for name, e in header.items()}
            end = max((entry[3] for entry in self._header.values()), default=0)
        except (KeyError, TypeError, IndexError) as e:
            raise ValueError(f"{self.path}: malformed safetensors header ({type(e).__name__}: {e})") from e
        if end != self._data_size:  # safetensors' data ends where the file does: a cut or padded file
            raise ValueError(f"{self.path}: its tensors end at byte {end} of {self._data_size} data bytes")

    def _entry(self, name: str) -> tuple[torch.dtype, tuple[int, ...], int, int]:
        """(dtype, shape, first byte, end byte in the file) of tensor ``name``, checked when
        used: a reader uses a few of the file's tensors (KeyError if absent)."""
        entry = self._header[name]
        try:
            dtype_name, shape, lo, hi = entry
            dtype = DTYPES[dtype_name]
            if not all(type(x) is int and x >= 0 for x in (*shape, lo, hi)):
                raise TypeError("shape and offsets must be non-negative integers")
        except (KeyError, TypeError, ValueError) as e:
            raise ValueError(f"{self.path}: malformed header entry {name!r}: {entry!r} ({e})") from e
        if hi - lo != math.prod(shape) * dtype.itemsize or hi > self._data_size or lo > hi:
            raise ValueError(f"{self.path}: tensor {name!r} ({dtype_name} {list(shape)}) does not fit bytes "
                             f"{lo}..{hi} of {self._data_size}")  # fmt: skip
        return dtype, shape, self._data + lo, self._data + hi

    def keys(self) -> list[str]:
        return list(self._header)

    def __contains__(self, name: str) -> bool:
        return name in self._header

    def dtype(self, name: str) -> torch.dtype:
        entry = self._header[name]
        try:
            return DTYPES[entry[0]]
        except (KeyError, TypeError) as e:
            raise ValueError(f"{self.path}: tensor {name!r} of no known dtype: {entry!r}") from e

    def shape(self, name: str) -> tuple[int, ...]:
        return self._entry(name)[1]

    def read(self, name: str, rows: slice | None = None) -> torch.Tensor:
        """Tensor ``name`` (KeyError if absent), or only ``rows`` of its first dimension (a
        slice with step 1, clamped to the tensor). Raises :class:`FileChangedError` when the
        file is not the one parsed any more, OSError when it cannot be read."""
        dtype, shape, lo, hi = self._entry(name)
        if rows is not None:
            if not shape:
                raise ValueError(f"TensorFile.read: {name!r} is a scalar, it has no rows")
            start, stop, step = rows.indices(shape[0])
            if step != 1:
                raise ValueError(f"TensorFile.read: rows must be a slice with step 1, got {rows}")
            row = (hi - lo) // shape[0] if shape[0] else 0
            shape, lo = (max(stop - start, 0), *shape[1:]), lo + start * row
            hi = lo + shape[0] * row
        buffer = bytearray(hi - lo)
        fd = os.open(self.path, os.O_RDONLY)
        try:
            now = stat_stamp(os.fstat(fd))
            if now != self._stamp:
                raise FileChangedError(f"{self.path} changed since it was opened (size, modification time, "
                                       f"inode {self._stamp} -> {now})")  # fmt: skip
            got = os.preadv(fd, [buffer], lo) if buffer else 0
        finally:
            os.close(fd)
        if got != len(buffer):
            raise FileChangedError(f"{self.path}: read {got} of {len(buffer)} bytes of {name!r} (the file was cut short)")
        return torch.frombuffer(buffer, dtype=dtype).reshape(shape) if buffer else torch.zeros(shape, dtype=dtype)

