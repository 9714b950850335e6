"""TensorFile: safetensors read with positioned reads, against the safetensors library."""

import json
import os
import struct

import pytest
import torch
from safetensors.torch import load_file, save_file

from gensplat_transforms.core.tensor_file import DTYPES, FileChangedError, TensorFile


@pytest.fixture
def tensors():
    g = torch.Generator().manual_seed(0)
    return {
        "f64": torch.randn(3, 4, dtype=torch.float64, generator=g),
        "f16": torch.randn(5, 2, generator=g).half(),
        "bf16": torch.randn(7, generator=g).bfloat16(),
        "u16": torch.randint(0, 2**16, (4, 3), generator=g).to(torch.uint16),
        "i8": torch.randint(-128, 128, (9,), generator=g).to(torch.int8),
        "u8": torch.randint(0, 256, (6, 1, 2), generator=g).to(torch.uint8),
        "bool": torch.rand(4, generator=g) > 0.5,
        "scalar": torch.tensor(2.5),
        "empty": torch.zeros(0, 3),
    }


def test_every_tensor_reads_as_safetensors_reads_it(tmp_path, tensors):
    path = tmp_path / "t.safetensors"
    save_file(tensors, str(path), metadata={"format": "x"})
    f, want = TensorFile(path), load_file(str(path))
    assert f.metadata == {"format": "x"} and sorted(f.keys()) == sorted(tensors)
    for name, t in want.items():
        got = f.read(name)
        assert got.dtype == t.dtype == f.dtype(name) and got.shape == t.shape and f.shape(name) == tuple(t.shape)
        assert torch.equal(got.view(torch.uint8) if t.ndim else got, t.view(torch.uint8) if t.ndim else t)
    assert torch.equal(f.read("f64", slice(1, 3)), tensors["f64"][1:3])
    assert torch.equal(f.read("u8", slice(4, 99)), tensors["u8"][4:])  # clamped
    assert f.read("u8", slice(9, 12)).shape == (0, 1, 2) and f.read("empty", slice(0, 5)).shape == (0, 3)
    with pytest.raises(ValueError, match="step 1"):
        f.read("u8", slice(0, 4, 2))
    with pytest.raises(ValueError, match="scalar"):
        f.read("scalar", slice(0, 1))
    with pytest.raises(KeyError):
        f.read("nope")


def _write(path, header: dict, body: bytes = b"") -> None:
    raw = json.dumps(header).encode()
    path.write_bytes(struct.pack("<Q", len(raw)) + raw + body)


ENTRY = {"dtype": "F32", "shape": [2], "data_offsets": [0, 8]}
MALFORMED_AT_OPEN = {
    "empty file": lambda p: p.write_bytes(b""),
    "7 bytes": lambda p: p.write_bytes(b"\x01" * 7),
    "header longer than the file": lambda p: p.write_bytes(struct.pack("<Q", 999) + b"{}"),
    "header not JSON": lambda p: p.write_bytes(struct.pack("<Q", 4) + b"{{{{"),
    "header not UTF-8": lambda p: p.write_bytes(struct.pack("<Q", 4) + b"\xff\xfe\xfd\xfc"),
    "header a list": lambda p: _write(p, []),  # type: ignore[arg-type]
    "metadata not str -> str": lambda p: _write(p, {"__metadata__": {"a": 1}, "x": ENTRY}, bytes(8)),
    "an entry without offsets": lambda p: _write(p, {"x": {"dtype": "F32", "shape": [2]}}, bytes(8)),
    "an entry that is a string": lambda p: _write(p, {"x": "F32"}, bytes(8)),
    "data cut short": lambda p: _write(p, {"x": ENTRY}, bytes(6)),
    "data padded": lambda p: _write(p, {"x": ENTRY}, bytes(12)),
}
MALFORMED_AT_READ = {
    "unknown dtype": {"dtype": "F8", "shape": [8], "data_offsets": [0, 8]},
    "size not the shape's": {"dtype": "F32", "shape": [3], "data_offsets": [0, 8]},
    "negative shape": {"dtype": "U8", "shape": [-8], "data_offsets": [0, 8]},
    "float shape": {"dtype": "U8", "shape": [8.0], "data_offsets": [0, 8]},
    "offsets reversed": {"dtype": "U8", "shape": [0], "data_offsets": [8, 0]},
}


@pytest.mark.parametrize("case", list(MALFORMED_AT_OPEN))
def test_a_malformed_file_is_refused_when_opened(tmp_path, case):
    path = tmp_path / "bad.safetensors"
    MALFORMED_AT_OPEN[case](path)
    with pytest.raises(ValueError, match=str(path)):
        TensorFile(path)


@pytest.mark.parametrize("case", list(MALFORMED_AT_READ))
def test_a_malformed_entry_is_refused_when_used(tmp_path, case):
    """A bad entry is refused by name when used; the file's other tensors still read."""
    path = tmp_path / "bad.safetensors"
    _write(path, {"bad": MALFORMED_AT_READ[case], "good": {"dtype": "U8", "shape": [8], "data_offsets": [0, 8]}},
           bytes(range(8)))  # fmt: skip
    f = TensorFile(path)
    assert torch.equal(f.read("good"), torch.arange(8, dtype=torch.uint8))
    with pytest.raises(ValueError, match="'bad'"):
        f.read("bad")
    if case == "unknown dtype":
        with pytest.raises(ValueError, match="no known dtype"):
            f.dtype("bad")


def test_a_file_changed_since_opened_is_never_read_as_the_old_one(tmp_path, tensors):
    """Replaced (a new inode), rewritten in place (a new size or modification time) or cut
    short: FileChangedError; removed: FileNotFoundError. Reading holds no descriptor."""
    path = tmp_path / "t.safetensors"
    save_file(tensors, str(path))
    f = TensorFile(path)
    fds = len(os.listdir("/proc/self/fd"))
    f.read("f64")
    assert len(os.listdir("/proc/self/fd")) == fds
    data = path.read_bytes()
    other = tmp_path / "other.safetensors"
    other.write_bytes(data)
    os.replace(other, path)  # same bytes, another file
    with pytest.raises(FileChangedError, match="changed since it was opened"):
        f.read("f64")
    f = TensorFile(path)
    st = path.stat()
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    with pytest.raises(FileChangedError):
        f.read("f64")
    f = TensorFile(path)
    with open(path, "r+b") as fh:
        fh.truncate(len(data) // 2)
    with pytest.raises(FileChangedError):
        f.read("f64")
    path.unlink()
    with pytest.raises(FileNotFoundError):
        f.read("f64")


def test_dtype_names_are_safetensors_own(tmp_path):
    """Every dtype name TensorFile knows is one the safetensors library writes for it."""
    for name, dtype in DTYPES.items():
        path = tmp_path / f"{name}.safetensors"
        save_file({"x": torch.zeros(2, dtype=dtype)}, str(path))
        (n,) = struct.unpack("<Q", path.read_bytes()[:8])
        assert json.loads(path.read_bytes()[8 : 8 + n])["x"]["dtype"] == name
