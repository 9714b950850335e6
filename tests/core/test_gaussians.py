"""Tests for gensplat_transforms.core.gaussians (container, safetensors and 3DGS PLY I/O)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from gensplat_transforms.core.gaussians import FORMAT_NAME, FORMAT_VERSION, Gaussians


def make(n: int = 6, degree: int = 1, seed: int = 0, dtype=torch.float32) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    return Gaussians(
        means=torch.randn(n, 3, generator=g, dtype=dtype),
        quats=torch.randn(n, 4, generator=g, dtype=dtype),
        scales=0.01 + torch.rand(n, 3, generator=g, dtype=dtype),
        opacities=0.01 + 0.98 * torch.rand(n, generator=g, dtype=dtype),
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g, dtype=dtype),
    )


def assert_same(a: Gaussians, b: Gaussians, **tol) -> None:
    assert len(a) == len(b)
    for name, t in a.tensors().items():
        torch.testing.assert_close(getattr(b, name), t, **tol, msg=lambda m, name=name: f"{name}: {m}")


# ---------------------------------------------------------------------------- validation
def _replace(name: str, fn):
    g = make(4, degree=1)
    fields = g.tensors()
    fields[name] = fn(fields[name])
    return fields


def _set(value, idx=(0, 0)):
    def fn(t):
        t = t.clone()
        t[idx] = value
        return t

    return fn


@pytest.mark.parametrize(
    ("name", "fn", "match"),
    [
        ("means", lambda t: t[:, :2], r"Gaussians.means: expected shape \(N, 3\)"),
        ("means", lambda t: t.reshape(-1), r"Gaussians.means: expected shape"),
        ("quats", lambda t: t[:, :3], r"Gaussians.quats: expected shape \(4, 4\), got \(4, 3\)"),
        ("quats", lambda t: t[:3], r"Gaussians.quats: expected shape"),
        ("scales", lambda t: t[:, :1], r"Gaussians.scales: expected shape"),
        ("opacities", lambda t: t[:, None], r"Gaussians.opacities: expected shape \(4,\)"),
        ("sh", lambda t: t[:, :3], r"Gaussians.sh: 3 SH coefficients"),
        ("sh", lambda t: t[..., :1], r"Gaussians.sh: expected shape"),
        ("sh", lambda t: torch.zeros(4, 36, 3), r"Gaussians.sh: 36 SH coefficients"),  # degree 5
        ("means", _set(float("nan")), r"Gaussians.means: 1 Gaussian\(s\) have NaN or Inf"),
        ("quats", _set(float("inf")), r"Gaussians.quats: .*NaN or Inf"),
        ("sh", _set(float("nan"), (2, 1, 0)), r"Gaussians.sh: 1 Gaussian\(s\) have NaN"),
        ("opacities", _set(float("nan"), 0), r"Gaussians.opacities: .*NaN"),
        ("scales", _set(-1e-3), r"Gaussians.scales: scales must be >= 0"),
        ("opacities", _set(1.01, 0), r"Gaussians.opacities: opacities must lie in \[0, 1\]"),
        ("opacities", _set(-0.01, 3), r"Gaussians.opacities: opacities must lie in \[0, 1\]"),
        ("means", lambda t: t.long(), r"Gaussians.means: expected a floating-point tensor"),
    ],
)
def test_invalid_fields_raise_naming_the_field(name, fn, match):
    with pytest.raises(ValueError, match=match):
        Gaussians(**_replace(name, fn))


def test_a_passed_check_is_remembered_until_a_tensor_changes():
    g = make(5)
    assert g._checked is not None  # construction checked it
    g.means[2, 1] = float("nan")  # in-place through torch: the version counter moves
    with pytest.raises(ValueError, match=r"Gaussians.means: 1 Gaussian\(s\) have NaN"):
        g.check()
    g = make(5)
    g.opacities = torch.full((5,), 2.0)  # a replaced tensor
    with pytest.raises(ValueError, match=r"opacities must lie in \[0, 1\]"):
        g.check()
    g = make(5)
    g.scales.numpy()[0, 0] = -1.0  # invisible to torch: only a forced check sees it
    g.check()
    with pytest.raises(ValueError, match=r"scales must be >= 0"):
        g.check(force=True)


def test_gaussians_of_inference_mode_tensors_work_and_are_checked_every_time():
    """Inference-mode tensors (LeRobot evaluates under torch.inference_mode) have no version
    counter: construction, cat, rendering and rechecks work, and every check scans."""
    from gensplat_transforms import Cameras, look_at, render

    with torch.inference_mode():
        g = make(5)
        assert g._checked is None and len(Gaussians.cat([g, make(2)])) == 7
        g.means[1, 0] = float("nan")
        with pytest.raises(ValueError, match=r"Gaussians.means: 1 Gaussian\(s\) have NaN"):
            g.check()
        camera = Cameras.from_intrinsics(20.0, 20.0, 8.0, 8.0, look_at((0, -1, 0), (0, 0, 0)), 16, 16)
        out = render(make(5), camera, backend="fast")
        assert torch.isfinite(out.rgb).all()


def test_cat_of_checked_gaussians_stays_checked():
    a, b = make(3), make(4, degree=2)
    assert Gaussians.cat([a, b])._checked is not None
    unchecked = Gaussians(**b.tensors(), validate=False)
    assert Gaussians.cat([a, unchecked])._checked is None


def test_boundary_values_are_valid():
    g = make(3)
    g = Gaussians(g.means, g.quats * 0, g.scales * 0, torch.tensor([0.0, 1.0, 0.5]), g.sh)  # zero quats ok
    assert len(g) == 3
    assert len(Gaussians.empty(sh_degree=3)) == 0 and Gaussians.empty(sh_degree=3).sh_degree == 3


# ---------------------------------------------------------------------------- selection / cat
def test_indexing_and_masking():
    g = make(6, degree=2)
    mask = torch.tensor([True, False, True, True, False, False])
    for index, rows in [
        (mask, [0, 2, 3]),
        (torch.tensor([5, 0]), [5, 0]),
        (slice(1, 3), [1, 2]),
        (4, [4]),
        (-1, [5]),
    ]:
        sub = g[index]
        assert len(sub) == len(rows) and sub.sh_degree == 2
        for name, t in g.tensors().items():
            torch.testing.assert_close(getattr(sub, name), t[rows])
        sub.check()  # still a valid container (an int index keeps the leading dimension)
    with pytest.raises(IndexError):
        g[6]


def test_cat_pads_sh_to_the_highest_degree():
    a, b = make(2, degree=0, seed=1), make(3, degree=2, seed=2)
    c = Gaussians.cat([a, b])
    assert len(c) == 5 and c.sh_degree == 2
    torch.testing.assert_close(c.sh[:2, :1], a.sh)
    assert (c.sh[:2, 1:] == 0).all()
    torch.testing.assert_close(c.sh[2:], b.sh)
    torch.testing.assert_close(c.means, torch.cat([a.means, b.means]))
    c.check()
    with pytest.raises(ValueError, match="nothing to concatenate"):
        Gaussians.cat([])


def test_with_sh_degree_truncates_and_pads():
    g = make(3, degree=3)
    assert g.with_sh_degree(1).sh.shape == (3, 4, 3)
    torch.testing.assert_close(g.with_sh_degree(1).sh, g.sh[:, :4])
    padded = g.with_sh_degree(4)
    assert padded.sh_degree == 4 and (padded.sh[:, 16:] == 0).all()
    for bad in (-1, 5):
        with pytest.raises(ValueError, match="degree must be in 0..4"):
            g.with_sh_degree(bad)


def test_prune_drops_low_opacity():
    g = make(5)
    g = Gaussians(g.means, g.quats, g.scales, torch.tensor([0.0, 1 / 255, 0.5, 0.003, 1.0]), g.sh)
    kept = g.prune()
    torch.testing.assert_close(kept.opacities, torch.tensor([1 / 255, 0.5, 1.0]))
    torch.testing.assert_close(kept.means, g.means[[1, 2, 4]])
    assert len(g.prune(0.6)) == 1


def test_to_dtype():
    g = make(4, degree=1)
    g64 = g.to(dtype=torch.float64)
    assert g64.dtype == torch.float64 and all(t.dtype == torch.float64 for t in g64.tensors().values())
    assert_same(g, g64.to(dtype=torch.float32), rtol=0, atol=0)


# ---------------------------------------------------------------------------- safetensors
def test_save_load_round_trip_with_metadata(tmp_path):
    g = make(7, degree=3)
    path = tmp_path / "scene.safetensors"
    g.save(path, {"episode": "3", "source": "droid"})
    loaded, meta = Gaussians.load(path)
    assert_same(g, loaded, rtol=0, atol=0)
    assert meta == {
        "episode": "3",
        "source": "droid",
        "format": FORMAT_NAME,
        "format_version": str(FORMAT_VERSION),
    }
    assert [p.name for p in tmp_path.iterdir()] == ["scene.safetensors"]  # no temporary file left behind


def test_metadata_cannot_break_the_format_header(tmp_path):
    path = tmp_path / "g.safetensors"
    make(2).save(path, {"format": "mine", "format_version": "99"})
    _, meta = Gaussians.load(path)
    assert meta["format"] == FORMAT_NAME and meta["format_version"] == str(FORMAT_VERSION)
    with pytest.raises(TypeError, match="metadata"):
        make(2).save(path, {"episode": 3})


def _write_raw(path, tensors, meta):
    save_file({k: v.contiguous() for k, v in tensors.items()}, str(path), metadata=meta)
    return path


@pytest.mark.parametrize(
    ("meta", "drop", "match"),
    [
        ({"format": "other"}, None, "not a Gaussians file"),
        (None, None, "not a Gaussians file"),
        (
            {"format": FORMAT_NAME, "format_version": "2"},
            None,
            "format version 2 is not the supported version 1",
        ),
        ({"format": FORMAT_NAME, "format_version": "one"}, None, "format version"),
        ({"format": FORMAT_NAME}, None, "format version"),
        ({"format": FORMAT_NAME, "format_version": str(FORMAT_VERSION)}, "sh", r"missing tensors \['sh'\]"),
    ],
)
def test_load_detects_wrong_format_version_and_content(tmp_path, meta, drop, match):
    tensors = make(3).tensors()
    tensors.pop(drop, None)
    path = _write_raw(tmp_path / "x.safetensors", tensors, meta)
    with pytest.raises(ValueError, match=match):
        Gaussians.load(path)


@pytest.mark.parametrize(
    ("field", "fn", "match"),
    [("opacities", lambda t: t + 2, "Gaussians.opacities"),
     ("sh", lambda t: t / 0, r"Gaussians.sh: 3 Gaussian\(s\) have NaN"),
     ("means", lambda t: t.long(), "Gaussians.means: expected a floating-point tensor")],
)  # fmt: skip
def test_load_validates_the_tensors_naming_the_file(tmp_path, field, fn, match):
    tensors = make(3).tensors()
    tensors[field] = fn(tensors[field])
    meta = {"format": FORMAT_NAME, "format_version": str(FORMAT_VERSION)}
    path = _write_raw(tmp_path / "x.safetensors", tensors, meta)
    with pytest.raises(ValueError, match=match) as error:
        Gaussians.load(path)
    assert str(error.value).startswith(f"{path}: ")


@pytest.mark.parametrize("keep", [0, 5, 8, 40, 0.5, -1])
def test_truncated_file_raises_value_error(tmp_path, keep):
    path = tmp_path / "g.safetensors"
    make(8, degree=2).save(path)
    data = path.read_bytes()
    cut = int(len(data) * keep) if isinstance(keep, float) else (len(data) + keep if keep < 0 else keep)
    path.write_bytes(data[:cut])
    with pytest.raises(ValueError, match="safetensors"):
        Gaussians.load(path)


@pytest.mark.parametrize(
    "content", [b"hello, not a tensor file", bytes(range(256)) * 4, b"\x10" + b"\x00" * 7 + b"{}"]
)
def test_garbage_file_raises_value_error(tmp_path, content):
    path = tmp_path / "g.safetensors"
    path.write_bytes(content)
    with pytest.raises(ValueError):
        Gaussians.load(path)


def test_missing_file_raises_file_not_found(tmp_path):
    with pytest.raises(FileNotFoundError):
        Gaussians.load(tmp_path / "nope.safetensors")


# ---------------------------------------------------------------------------- PLY
def read_ply(path) -> tuple[list[str], np.ndarray]:
    """Minimal independent reader: header lines and the float32 vertex table."""
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    names = [line.split()[2] for line in header if line.startswith("property float ")]
    n = int(next(line.split()[2] for line in header if line.startswith("element vertex")))
    return header, np.frombuffer(data[end:], dtype=[(p, "<f4") for p in names], count=n)


@pytest.mark.parametrize("degree", [0, 1, 3, 4])
def test_ply_round_trip_and_standard_3dgs_layout(tmp_path, degree):
    g = make(9, degree=degree, seed=degree)
    path = tmp_path / "scene.ply"
    g.to_ply(path)
    header, arr = read_ply(path)
    k = (degree + 1) ** 2
    expected = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    expected += [f"f_rest_{i}" for i in range(3 * (k - 1))]
    expected += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert header[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 9"]
    assert list(arr.dtype.names) == expected and header[-1] == "end_header"
    assert len(path.read_bytes()) == len("\n".join(header)) + 1 + 9 * 4 * len(
        expected
    )  # nothing after the table
    # stored values: logit opacity, log scale, w-x-y-z rotation, channel-major f_rest
    np.testing.assert_allclose(
        arr["opacity"], torch.logit(g.opacities.double()).numpy(), rtol=1e-5, atol=1e-5
    )
    np.testing.assert_allclose(arr["scale_1"], torch.log(g.scales[:, 1]).numpy(), rtol=1e-6)
    np.testing.assert_array_equal(arr["rot_0"], g.quats[:, 0].numpy())
    np.testing.assert_array_equal(arr["f_dc_2"], g.sh[:, 0, 2].numpy())
    for c in range(3):
        for j in range(1, k):
            np.testing.assert_array_equal(arr[f"f_rest_{c * (k - 1) + j - 1}"], g.sh[:, j, c].numpy())
    assert (arr["nx"] == 0).all()
    back = Gaussians.from_ply(path)
    assert back.sh_degree == degree
    torch.testing.assert_close(back.means, g.means, rtol=0, atol=0)
    torch.testing.assert_close(back.quats, g.quats, rtol=0, atol=0)
    torch.testing.assert_close(back.sh, g.sh, rtol=0, atol=0)
    torch.testing.assert_close(back.scales, g.scales, rtol=1e-6, atol=0)
    torch.testing.assert_close(back.opacities, g.opacities, rtol=0, atol=1e-6)


def test_ply_round_trip_of_extreme_values(tmp_path):
    g = make(3, degree=0)
    g = Gaussians(g.means, g.quats, torch.tensor([[0.0, 1e-6, 3.0]] * 3), torch.tensor([0.0, 1.0, 0.5]), g.sh)
    g.to_ply(tmp_path / "e.ply")
    back = Gaussians.from_ply(tmp_path / "e.ply")
    torch.testing.assert_close(back.opacities, g.opacities, rtol=0, atol=1e-6)
    torch.testing.assert_close(back.scales, g.scales, rtol=1e-5, atol=1e-12)


def test_ply_of_float64_gaussians(tmp_path):
    g = make(4, degree=1, dtype=torch.float64)
    g.to_ply(tmp_path / "d.ply")
    back = Gaussians.from_ply(tmp_path / "d.ply")
    assert back.dtype == torch.float32
    assert_same(g.to(dtype=torch.float32), back, rtol=1e-5, atol=1e-6)


def _ply(header_lines: list[str], body: bytes) -> bytes:
    return ("\n".join(header_lines) + "\nend_header\n").encode("ascii") + body


def test_ply_reader_ignores_other_elements_and_reads_doubles(tmp_path):
    names = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2"]
    names += ["rot_0", "rot_1", "rot_2", "rot_3"]
    row = np.array(
        [(0.1, 0.2, 0.3, 1.0, 2.0, 3.0, 0.0, -1.0, -2.0, -3.0, 1.0, 0.0, 0.0, 0.0)],
        dtype=[(n, "<f8") for n in names],
    )
    header = ["ply", "format binary_little_endian 1.0", "comment made by a test", "element vertex 1"]
    header += [f"property double {n}" for n in names]
    header += ["element face 0", "property list uchar int vertex_indices"]
    path = tmp_path / "doubles.ply"
    path.write_bytes(_ply(header, row.tobytes()))
    g = Gaussians.from_ply(path)
    torch.testing.assert_close(g.means, torch.tensor([[0.1, 0.2, 0.3]]))
    torch.testing.assert_close(g.opacities, torch.tensor([0.5]))
    torch.testing.assert_close(g.scales, torch.exp(torch.tensor([[-1.0, -2.0, -3.0]])))
    assert g.sh.shape == (1, 1, 3)


def test_ply_reader_reads_ascii_and_big_endian_and_refuses_vertex_lists(tmp_path):
    from plyfile import PlyData, PlyElement

    g = make(5, degree=1)
    g.to_ply(tmp_path / "scene.ply")
    vertex = PlyData.read(str(tmp_path / "scene.ply"))["vertex"]
    for name, kw in [("ascii", {"text": True}), ("big", {"byte_order": ">"})]:
        PlyData([vertex], **kw).write(str(tmp_path / f"{name}.ply"))
        assert_same(Gaussians.from_ply(tmp_path / f"{name}.ply"), Gaussians.from_ply(tmp_path / "scene.ply"),
                    rtol=0, atol=0)  # fmt: skip
    table = vertex.data
    rows = np.empty(len(table), dtype=table.dtype.descr + [("ids", "O")])
    for n in table.dtype.names:
        rows[n] = table[n]
    rows["ids"] = [np.array([i], dtype=np.int32) for i in range(len(table))]
    PlyData([PlyElement.describe(rows, "vertex")]).write(str(tmp_path / "lists.ply"))
    with pytest.raises(ValueError, match=r"lists.ply: unsupported PLY vertex list properties \['ids'\]"):
        Gaussians.from_ply(tmp_path / "lists.ply")


_BAD_PLY = ["truncated", "garbage", "ascii", "no_end", "missing_rot", "odd_f_rest", "vertex_not_first",
            "negative_count", "float_count", "empty_count", "empty_element", "non_ascii_header",
            "property_without_name", "list_property", "duplicate_property", "nan_value",
            "overflowing_log_scale"]  # fmt: skip


@pytest.mark.parametrize("case", _BAD_PLY)
def test_bad_ply_files_raise_value_error_naming_the_file(tmp_path, case):
    good = tmp_path / "good.ply"
    make(4, degree=1).to_ply(good)
    data = good.read_bytes()
    header_end = data.index(b"end_header\n")
    body_start = header_end + len(b"end_header\n")
    huge_scale = read_ply(good)[1].copy()
    huge_scale["scale_0"][1] = 100.0  # a log-scale whose exp overflows float32
    cases = {
        "truncated": (data[:-5], r"the header declares 4 vertex \(416 bytes\) but the body has 411 bytes"),
        "garbage": (b"\x00\x01 not a ply at all", "expected 'ply'"),
        "ascii": (data.replace(b"binary_little_endian", b"ascii", 1), "not a readable PLY file"),
        "no_end": (data[:header_end], "early end-of-file"),
        "missing_rot": (
            data.replace(b"property float rot_3\n", b"", 1),
            r"lacks 3DGS properties \['rot_3'\]",
        ),
        "odd_f_rest": (data.replace(b"property float f_rest_8\n", b"", 1), "not a multiple of 3"),
        "vertex_not_first": (
            data.replace(b"element vertex", b"element face 0\nelement vertex", 1),
            "'vertex' element",
        ),
        "negative_count": (data.replace(b"element vertex 4", b"element vertex -5", 1), "negative dimensions"),
        "float_count": (data.replace(b"element vertex 4", b"element vertex 1e3", 1), "expected integer count"),
        "empty_count": (data.replace(b"element vertex 4", b"element vertex", 1), "expected \"element {name}"),
        "empty_element": (data.replace(b"element vertex 4", b"element", 1), "expected \"element {name}"),
        "non_ascii_header": (data.replace(b"ply\n", "ply\ncomment caf\u00e9\n".encode(), 1), "'ascii' codec can't decode"),
        "property_without_name": (data.replace(b"property float rot_3", b"property float", 1), "bad 'property' line"),
        "list_property": (
            data.replace(b"property float rot_3", b"property list uchar float rot_3", 1), "early end-of-file"
        ),
        "duplicate_property": (
            data.replace(b"property float rot_3", b"property float rot_2", 1), "two properties with same name"
        ),
        "nan_value": (data[:-4] + np.float32(np.nan).tobytes(), r"Gaussians.quats: 1 Gaussian\(s\) have NaN"),
        "overflowing_log_scale": (data[:body_start] + huge_scale.tobytes(), r"Gaussians.scales: .*Inf"),
    }
    assert sorted(cases) == sorted(_BAD_PLY)
    content, match = cases[case]
    path = tmp_path / f"{case}.ply"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=match) as error:
        Gaussians.from_ply(path)
    assert str(error.value).startswith(f"{path}: ")
