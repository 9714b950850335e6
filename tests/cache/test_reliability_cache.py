"""Issue 41 for the cache and depth import: nothing a user types harms the dataset, and every
mistake gets a clear message (sidecars checked against where they are read, stray files, the
--copy-depth setting, the build lock, the depth codec's checksums, import-depth's inputs and
gensplat cache's options)."""

import os
import shutil
import threading

import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
os.environ["HF_HUB_OFFLINE"] = "1"

from gensplat_cli import main

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.data.format import depth_path

REPO = "local/reliability"
#: the recorded dataset (``scene_dataset``): 2 episodes of 6 frames at 32x32, RGB-D
SCENE = {"repo": REPO, "episodes": 2, "frames": 6, "size": 32}


@pytest.fixture
def root(scene_dataset, dataset_copy):
    """A fresh copy of the recorded SCENE, to change."""
    return dataset_copy(scene_dataset(**SCENE))


def cache(root, *options: str) -> int:
    return main(["cache", "--root", str(root), "--repo-id", REPO, *options])


def error_line(capsys) -> str:
    """The one ``gensplat: error:`` line of stderr (after any progress bars)."""
    err = capsys.readouterr().err
    assert err.endswith("\n") and err.splitlines()[-1].startswith("gensplat: error: "), err
    return err.splitlines()[-1]


def test_a_sidecar_of_another_camera_is_refused_naming_what_it_claims(root, capsys):
    shutil.copyfile(depth_path(root, "right", 0), depth_path(root, "left", 0))
    assert cache(root) == 2
    err = error_line(capsys)
    assert f"{depth_path(root, 'left', 0)}" in err and "camera 'right'" in err and "expected camera 'left'" in err


def test_a_stray_file_in_a_depth_folder_keeps_the_cache(root, scene_dataset):
    from gensplat_lerobot import LeRobotSource
    from gensplat_lerobot.source import files_digest

    before = LeRobotSource(root, REPO).fingerprint
    plain = files_digest(root, "depth/left")
    (root / "depth" / "left" / "README.txt").write_text("depth of the left camera, from the RealSense\n")
    (root / "depth" / "left" / "notes").mkdir()
    (root / "depth" / "left" / "notes" / "episode_000000.safetensors").write_bytes(b"not a sidecar of the folder")
    assert files_digest(root, "depth/left") == plain
    assert LeRobotSource(root, REPO).fingerprint == before == LeRobotSource(scene_dataset(**SCENE), REPO).fingerprint
    (root / "depth" / "left" / "episode_000009.safetensors").write_bytes(b"a new sidecar")
    assert files_digest(root, "depth/left") != plain


def test_copy_depth_is_kept_for_the_episodes_training_builds(root):
    from gensplat_lerobot import enable_gensplat
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from safetensors import safe_open

    assert cache(root, "--copy-depth", "--episodes", "0", "--probability", "1") == 0
    ds = enable_gensplat(LeRobotDataset(REPO, root=root))
    assert not ds.gensplat.cache.link_depth
    ds[len(ds) - 1]  # episode 1: built by the transform
    for episode in (0, 1):
        with safe_open(str(ds.gensplat.cache.path(episode)), framework="pt") as f:
            assert "depth_links" not in f.metadata() and "depth.reference" in f.keys()  # noqa: SIM118 (safe_open is no dict)


def test_a_removed_lock_file_lets_no_second_builder_in(tmp_path):
    """A builder holds an episode's lock; the lock file is deleted; a second builder gets a
    new lock file and builds the episode: the first, resumed, finds it built."""
    from gensplat_transforms import RGBDReconstructor
    from gensplat_transforms.cache.store import SceneCache

    source = SceneEpisodes(num_episodes=1, num_frames=2, size=16)
    entered, resume = threading.Event(), threading.Event()

    class Paused:  # the source, its first num_frames call waiting (the first builder holds the lock there)
        def __getattr__(self, name):
            return getattr(source, name)

        def num_frames(self, episode):
            if not entered.is_set():
                entered.set()
                assert resume.wait(30)
            return source.num_frames(episode)

    def builder():
        return SceneCache(tmp_path, RGBDReconstructor(), source.fingerprint)

    results = []
    first = threading.Thread(target=lambda: results.append(builder().ensure(0, Paused())))
    first.start()
    assert entered.wait(30)
    (tmp_path / ".episode_000000.lock").unlink()
    second = builder().ensure(0, source)
    resume.set()
    first.join(30)
    assert second is not None and results == [None]  # built once
    assert builder().status(0) == "ok"


def test_every_bit_flip_of_compressed_depth_is_refused_or_harmless():
    """The depth codec's blobs carry a checksum: a flipped bit never decodes to other depth
    (ValueError, which the cache reports as a corrupt file to rebuild); old blobs still decode."""
    import numpy as np
    import torch

    from gensplat_transforms.cache import depth_codec as dc

    depth = 0.5 + torch.rand(3, 2, 12, 16, generator=torch.Generator().manual_seed(0))
    ref, blobs = dc.encode_episode(depth)
    rows = dc.reference_rows(ref, (2, 12, 16))
    want = dc.decode_codes(rows, blobs[1])
    changed = 0
    for bit in range(8 * len(blobs[1])):
        flipped = bytearray(blobs[1])
        flipped[bit // 8] ^= 1 << bit % 8
        try:
            changed += not np.array_equal(dc.decode_codes(rows, bytes(flipped)), want)
        except ValueError:
            pass
    assert changed == 0
    unchecked = dc.zstandard.ZstdCompressor(level=6).compress(np.diff(want, axis=-1, prepend=np.uint16(0)).tobytes())
    assert np.array_equal(dc.decode_codes(rows * 0, unchecked, "zstd"), want)  # written before the checksum


T, H, W = 6, 32, 32  # the recorded dataset's episodes and images


def import_depth(root, source, *options: str) -> int:
    return main(["import-depth", "--root", str(root), "--repo-id", REPO, "--camera", "left", "--from", str(source),
                 "--episodes", "0", "--overwrite", *options])  # fmt: skip


def test_8_bit_depth_needs_its_units(root, tmp_path, capsys):
    import numpy as np

    from gensplat_transforms.data.format import load_depth

    np.save(tmp_path / "ep0.npy", np.full((T, H, W), 92, np.uint8))  # centimetres
    assert import_depth(root, tmp_path / "ep{episode}.npy") == 2
    line = error_line(capsys)
    assert "8-bit values" in line and "--units cm" in line
    assert import_depth(root, tmp_path / "ep{episode}.npy", "--units", "cm") == 0
    assert abs(float(load_depth(root, "left", 0).median()) - 0.92) < 1e-3


def test_an_npz_is_checked_before_it_is_decompressed(root, tmp_path, capsys):
    import tracemalloc

    import numpy as np

    np.savez_compressed(tmp_path / "ep0.npz", depth=np.zeros((200, 500, 500), np.uint16))  # 100 MB, 100 kB packed
    assert (tmp_path / "ep0.npz").stat().st_size < 1e6
    tracemalloc.start()
    try:
        assert import_depth(root, tmp_path / "ep{episode}.npz") == 2
        assert tracemalloc.get_traced_memory()[1] < 20e6
    finally:
        tracemalloc.stop()
    assert f"depth of shape (200, 500, 500), expected ({T}, {H}, {W})" in error_line(capsys)


def test_a_pickled_npz_member_is_refused(root, tmp_path, capsys):
    import numpy as np

    np.savez(tmp_path / "ep0.npz", depth=np.array([{"depth": 1}] * T, dtype=object))
    assert import_depth(root, tmp_path / "ep{episode}.npz") == 2
    assert "expected integers or floats (pickled objects are not read)" in error_line(capsys)


def test_an_npy_header_claiming_a_huge_shape_is_refused(root, tmp_path, capsys):
    import numpy as np

    with open(tmp_path / "ep0.npy", "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": (10**6,) * 3})
        f.write(bytes(64))
    assert import_depth(root, tmp_path / "ep{episode}.npy") == 2
    assert "depth of shape (1000000, 1000000, 1000000), expected" in error_line(capsys)


def test_a_truncated_npz_is_refused(root, tmp_path, capsys):
    import numpy as np

    np.savez(tmp_path / "ep0.npz", depth=np.ones((T, H, W), np.float32))
    data = (tmp_path / "ep0.npz").read_bytes()
    (tmp_path / "ep0.npz").write_bytes(data[: len(data) // 2])
    assert import_depth(root, tmp_path / "ep{episode}.npz") == 2
    assert f"{tmp_path / 'ep0.npz'}: unreadable depth array" in error_line(capsys)


def test_a_png_over_pillows_pixel_limit_is_refused(root, tmp_path, capsys, monkeypatch):
    import numpy as np
    from PIL import Image

    (tmp_path / "ep0").mkdir()
    for t in range(T):
        Image.fromarray(np.full((H, W), 900, np.uint16)).save(tmp_path / "ep0" / f"{t}.png")
    monkeypatch.setattr(Image, "MAX_IMAGE_PIXELS", 400)  # a 32x32 image counts as a bomb
    assert import_depth(root, tmp_path / "ep{episode}") == 2
    assert "0.png: unreadable image (Image size (1024 pixels) exceeds limit" in error_line(capsys)


def test_a_file_where_the_depth_folder_goes_is_refused(root, tmp_path, capsys):
    import numpy as np

    np.save(tmp_path / "ep0.npy", np.full((T, H, W), 0.9, np.float32))
    shutil.rmtree(root / "depth" / "left")
    (root / "depth" / "left").write_text("not a folder")
    assert import_depth(root, tmp_path / "ep{episode}.npy") == 2
    assert f"{root / 'depth' / 'left'} is a file where the folder of depth sidecars goes" in error_line(capsys)


@pytest.mark.parametrize("options, message", [
    (["--episodes", "0", "99"], "episode(s) [99] are not in the dataset (episodes 0..1)"),
    (["--cameras", "nope", "right"], "no camera(s) ['nope']; its cameras: ['left', 'right', 'front']"),
    (["--level", "bogus"], "unknown perturbation level 'bogus'"),
    (["--probability", "1.5"], "probability must be in [0, 1], got 1.5"),
    (["--cameras", "left", "left"], "--cameras names ['left'] more than once"),  # reconstructed twice before
    (["--replace", "right", "right"], "GenSplatConfig.replace names ['right'] more than once"),
])  # fmt: skip
def test_cache_options_are_checked_before_anything_is_written(root, capsys, options, message):
    assert cache(root, *options) == 2
    assert message in error_line(capsys)
    assert not (root / "gensplat").exists()


def test_the_gsplat_backend_without_cuda_is_refused_up_front(root, capsys, monkeypatch):
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert cache(root, "--backend", "gsplat") == 2
    assert "gsplat backend needs CUDA" in error_line(capsys) and not (root / "gensplat").exists()


def test_an_empty_dataset_is_refused(root, capsys, monkeypatch):
    from gensplat_lerobot import dataset

    monkeypatch.setattr(dataset, "episode_table", lambda meta: {"episode_index": [], "length": []})
    assert cache(root) == 2
    assert "has no episodes" in error_line(capsys) and not (root / "gensplat").exists()


def test_a_garbled_dataset_record_gives_the_stale_cache_message(root):
    from gensplat_lerobot import enable_gensplat
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from gensplat_transforms.cache.store import StaleCacheError
    from gensplat_transforms.data.format import load_depth, save_depth

    assert cache(root) == 0
    save_depth(root, "left", 1, load_depth(root, "left", 1)[:, 0] + 0.01)
    (root / "gensplat" / "dataset.json").write_text("{garbled")
    with pytest.raises(StaleCacheError, match="changed since its GenSplat cache was built"):
        enable_gensplat(LeRobotDataset(REPO, root=root))
