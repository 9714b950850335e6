"""gensplat import-depth: recorded depth (PNG, TIFF, .npy, .npz) -> a dataset's depth sidecars."""

import os

import numpy as np
import pytest
import torch
from PIL import Image

from gensplat_transforms.data.depth_import import import_depth
from gensplat_transforms.data.format import depth_path, load_depth

W, H, T = 12, 8, 11


@pytest.fixture
def depth_m():
    """(T, H, W) metres: a slanted plane 0.5-1.5 m, a few pixels without depth."""
    g = torch.Generator().manual_seed(0)
    d = 0.5 + torch.linspace(0, 1, W).expand(T, H, W) + 0.01 * torch.rand(T, H, W, generator=g)
    d[:, 0, :3] = 0
    return d


def write_pngs(folder, depth_m, scale=1e-3):
    """One 16-bit PNG per frame, named 0.png .. 10.png (not zero-padded)."""
    folder.mkdir(parents=True, exist_ok=True)
    for t, frame in enumerate(depth_m):
        Image.fromarray(np.rint(frame.numpy() / scale).astype(np.uint16)).save(folder / f"{t}.png")
    return folder


def run(tmp_path, source, lengths=None, **kw):
    return import_depth(tmp_path / "ds", "left", str(source), lengths or {0: T}, (W, H), progress=False, **kw)


def test_millimetre_pngs_in_natural_order_become_the_sidecar(tmp_path, depth_m):
    write_pngs(tmp_path / "raw" / "ep0", depth_m)
    (tmp_path / "raw" / "ep0" / "camera.json").write_text("{}")  # other files beside the frames: not read
    done = run(tmp_path, tmp_path / "raw" / "ep{episode}")
    got = load_depth(tmp_path / "ds", "left", 0)[:, 0]
    want = torch.from_numpy(np.rint(depth_m.numpy() * 1e3) * 1e-3).float()
    assert torch.allclose(got, want, rtol=1e-3, atol=0)  # float16, frames in order 0, 1, .., 10
    assert done[0].frames == T and done[0].invalid == 3 / (H * W) and 0.7 < done[0].median_m < 1.3
    assert not list((tmp_path / "ds").rglob("*.tmp"))


def test_arrays_per_episode_and_explicit_units(tmp_path, depth_m):
    np.save(tmp_path / "ep0.npy", depth_m.numpy())  # float metres
    np.savez(tmp_path / "ep1.npz", depth=(depth_m * 100).numpy(), other=np.zeros(3))  # centimetres
    np.save(tmp_path / "ep2.npy", np.rint(depth_m.numpy() * 1e4).astype(np.int32))  # 0.1 mm steps
    run(tmp_path, tmp_path / "ep{episode}.npy", {0: T})
    run(tmp_path, tmp_path / "ep{episode}.npz", {1: T}, units="cm")
    run(tmp_path, tmp_path / "ep{episode}.npy", {2: T}, units=1e-4)
    for e in range(3):
        assert torch.allclose(load_depth(tmp_path / "ds", "left", e)[:, 0], depth_m, rtol=1e-3, atol=1e-4)


def test_float_tiff_frames_by_glob(tmp_path, depth_m):
    folder = tmp_path / "raw" / "ep003"
    folder.mkdir(parents=True)
    for t, frame in enumerate(depth_m):
        Image.fromarray(frame.numpy()).save(folder / f"depth_{t:04d}.tiff")
    (folder / "notes.txt").write_text("ignored by the glob")
    run(tmp_path, tmp_path / "raw" / "ep{episode:03d}" / "depth_*.tiff", {3: T})
    assert torch.allclose(load_depth(tmp_path / "ds", "left", 3)[:, 0], depth_m, rtol=1e-3)


def test_invalid_values_become_no_depth(tmp_path, depth_m):
    d = depth_m.clone()
    d[1, 2, 2], d[2, 3, 3], d[3, 4, 4], d[4, 5, 5] = float("nan"), float("inf"), -1.0, 1e9
    np.save(tmp_path / "ep0.npy", d.numpy())
    run(tmp_path, tmp_path / "ep{episode}.npy")
    got = load_depth(tmp_path / "ds", "left", 0)[:, 0]
    assert torch.isfinite(got).all() and got[1, 2, 2] == got[2, 3, 3] == got[3, 4, 4] == 0
    assert got[4, 5, 5] == 6e4  # clamped to 60 km


def test_guessed_units_are_checked_and_explicit_ones_trusted(tmp_path, depth_m):
    np.save(tmp_path / "ep0.npy", (depth_m * 1000).numpy())  # float millimetres, read as metres
    with pytest.raises(ValueError, match=r"median depth \d{3,4}(\.\d+)? m with the values read as m; give the units"):
        run(tmp_path, tmp_path / "ep{episode}.npy")
    run(tmp_path, tmp_path / "ep{episode}.npy", units="mm")
    assert torch.allclose(load_depth(tmp_path / "ds", "left", 0)[:, 0], depth_m, rtol=1e-3)
    for bad in ("inch", 0, -1, float("nan")):
        with pytest.raises(ValueError, match="units|metres per unit"):
            run(tmp_path, tmp_path / "ep{episode}.npy", units=bad, overwrite=True)


MISTAKES = {
    "a frame missing": (lambda d, f: os.remove(f / "10.png"), ValueError, r"10 frames \(.*0\.png .. .*9\.png\); the dataset's episode has 11"),
    "another size": (lambda d, f: Image.fromarray(np.zeros((9, 12), np.uint16)).save(f / "5.png"), ValueError, "register the depth to the colour camera"),
    "an 8-bit image": (lambda d, f: Image.fromarray(np.zeros((H, W), np.uint8)).save(f / "5.png"), ValueError, "L image is not depth"),
    "a colour image": (lambda d, f: Image.fromarray(np.zeros((H, W, 3), np.uint8)).save(f / "5.png"), ValueError, "RGB image is not depth"),
    "a damaged image": (lambda d, f: (f / "5.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage"), ValueError, "unreadable image"),
    "another format": (lambda d, f: [p.rename(p.with_suffix(".exr")) for p in f.iterdir()], ValueError, r"0 frames of types .png.*\['.exr'\] not read"),
    "mixed value kinds": (lambda d, f: Image.fromarray(np.ones((H, W), np.float32)).save(f / "5.tiff") or os.remove(f / "5.png"), ValueError, "one kind of values"),
    "no folder": (lambda d, f: os.rename(f, f.with_name("elsewhere")), FileNotFoundError, "no such folder"),
}


@pytest.mark.parametrize("case", list(MISTAKES))
def test_a_mistaken_episode_is_refused_naming_it_and_nothing_is_written(tmp_path, depth_m, case):
    folder = write_pngs(tmp_path / "raw" / "ep0", depth_m)
    edit, error, message = MISTAKES[case]
    edit(depth_m, folder)
    with pytest.raises(error, match=message):
        run(tmp_path, tmp_path / "raw" / "ep{episode}")
    assert not depth_path(tmp_path / "ds", "left", 0).exists() and not list(tmp_path.rglob("*.tmp"))


def test_bad_arrays_and_sources_are_refused(tmp_path, depth_m):
    with pytest.raises(ValueError, match=r"must name the episode"):
        run(tmp_path, tmp_path / "ep0.npy")
    for bad in ("ep{episode}{camera}.npy", "ep{episode:q}.npy", "ep{0}{episode}.npy", "ep{episode.npy"):
        with pytest.raises(ValueError, match="is not a pattern of {episode}"):
            run(tmp_path, tmp_path / bad)
    np.savez(tmp_path / "ep0.npz", a=depth_m.numpy(), b=depth_m.numpy())
    with pytest.raises(ValueError, match=r"expected one array or one named 'depth'"):
        run(tmp_path, tmp_path / "ep{episode}.npz")
    np.save(tmp_path / "ep0.npy", depth_m[0].numpy())
    with pytest.raises(ValueError, match=r"must be \(T, H, W\)"):
        run(tmp_path, tmp_path / "ep{episode}.npy")
    np.save(tmp_path / "ep0.npy", np.array([{"depth": 1}] * T), allow_pickle=True)
    with pytest.raises(ValueError, match="unreadable depth array"):
        run(tmp_path, tmp_path / "ep{episode}.npy")
    np.save(tmp_path / "ep0.npy", np.zeros((T, H, W)))
    with pytest.raises(ValueError, match="no pixel of episode 0 has depth"):
        run(tmp_path, tmp_path / "ep{episode}.npy")
    with pytest.raises(FileNotFoundError, match="no such depth file"):
        run(tmp_path, tmp_path / "ep{episode}.npy", {7: T})


def test_existing_sidecars_are_kept_unless_damaged_or_overwritten(tmp_path, depth_m):
    np.save(tmp_path / "ep0.npy", depth_m.numpy())
    run(tmp_path, tmp_path / "ep{episode}.npy")
    path = depth_path(tmp_path / "ds", "left", 0)
    stamp = path.stat().st_mtime_ns
    np.save(tmp_path / "ep0.npy", (depth_m + 1).numpy())
    assert run(tmp_path, tmp_path / "ep{episode}.npy")[0].skipped and path.stat().st_mtime_ns == stamp
    assert not run(tmp_path, tmp_path / "ep{episode}.npy", overwrite=True)[0].skipped
    assert torch.allclose(load_depth(tmp_path / "ds", "left", 0)[:, 0], depth_m + 1, rtol=1e-3)
    path.write_bytes(b"damaged")
    assert not run(tmp_path, tmp_path / "ep{episode}.npy")[0].skipped
    assert torch.allclose(load_depth(tmp_path / "ds", "left", 0)[:, 0], depth_m + 1, rtol=1e-3)


def test_npz_members_named_without_the_npy_suffix_are_read(tmp_path, depth_m):
    """An archive written by hand (zipfile) names its member 'depth', not NumPy's 'depth.npy': read,
    not a raw KeyError; one that holds no array is a clear error."""
    import io
    import zipfile

    buffer = io.BytesIO()
    np.save(buffer, depth_m.numpy())
    with zipfile.ZipFile(tmp_path / "ep0.npz", "w") as z:
        z.writestr("depth", buffer.getvalue())
        z.writestr("notes.txt", b"recorded by hand")
    run(tmp_path, tmp_path / "ep{episode}.npz", {0: T})
    assert torch.allclose(load_depth(tmp_path / "ds", "left", 0)[:, 0], depth_m, rtol=1e-3, atol=1e-4)
    with zipfile.ZipFile(tmp_path / "ep1.npz", "w") as z:
        z.writestr("readme", b"no array here")
    with pytest.raises(ValueError, match=r"ep1.npz: unreadable depth array"):
        run(tmp_path, tmp_path / "ep{episode}.npz", {1: T})


def test_an_npz_claiming_a_huge_array_is_refused_from_its_header(tmp_path):
    """A member whose header says (61, 2500, 2500) (1.5 GB) is refused by its shape before any of
    it is decompressed: memory stays small."""
    import io
    import tracemalloc
    import zipfile

    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f4", "fortran_order": False, "shape": (61, 2500, 2500)})
    with (zipfile.ZipFile(tmp_path / "ep0.npz", "w", compression=zipfile.ZIP_DEFLATED) as z,
          z.open("depth.npy", "w", force_zip64=True) as f):  # fmt: skip
        f.write(header.getvalue())  # the magic and the header, as NumPy writes them
        for _ in range(64):
            f.write(bytes(1 << 20))  # 64 MB of zeros, a few kB compressed
    assert (tmp_path / "ep0.npz").stat().st_size < 1 << 20
    tracemalloc.start()
    with pytest.raises(ValueError, match=r"depth of shape \(61, 2500, 2500\), expected"):
        run(tmp_path, tmp_path / "ep{episode}.npz")
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 32 << 20


@pytest.mark.parametrize("link", ["camera", "depth"])
def test_a_depth_folder_linked_into_the_dataset_is_refused(tmp_path, depth_m, link):
    """depth/<camera> (or depth/) linked to another of the dataset's folders: the sidecars would
    land there (found by a hostile probe: files written into meta/)."""
    np.save(tmp_path / "ep0.npy", depth_m.numpy())
    meta = tmp_path / "ds" / "meta"
    meta.mkdir(parents=True)
    (meta / "info.json").write_text("{}")
    if link == "camera":
        (tmp_path / "ds" / "depth").mkdir()
        (tmp_path / "ds" / "depth" / "left").symlink_to(meta, target_is_directory=True)
    else:
        (meta / "left").mkdir()
        (tmp_path / "ds" / "depth").symlink_to(meta, target_is_directory=True)
    with pytest.raises(ValueError, match="symbolic link.*never writes into"):
        run(tmp_path, tmp_path / "ep{episode}.npy")
    assert sorted(p.name for p in meta.rglob("*")) == sorted(["info.json"] + (["left"] if link == "depth" else []))


def test_a_depth_folder_linked_to_another_disk_is_used(tmp_path, depth_m):
    np.save(tmp_path / "ep0.npy", depth_m.numpy())
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "depth").symlink_to(elsewhere, target_is_directory=True)
    run(tmp_path, tmp_path / "ep{episode}.npy")
    assert (elsewhere / "left" / "episode_000000.safetensors").is_file()
