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

from gensplat_lerobot.record import record_scene_dataset

from gensplat_transforms.cli import main
from gensplat_transforms.dataset_format import depth_path
from gensplat_transforms.episodes import SceneEpisodes

REPO = "local/reliability"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    root = tmp_path_factory.mktemp("lerobot") / "ds"
    record_scene_dataset(root, SceneEpisodes(num_episodes=2, num_frames=6, size=32), REPO, progress=False)
    return root


@pytest.fixture
def root(recorded, tmp_path):
    copy = tmp_path / "ds"
    shutil.copytree(recorded, copy)
    return copy


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


def test_a_stray_file_in_a_depth_folder_keeps_the_cache(root, recorded):
    from gensplat_lerobot import LeRobotSource
    from gensplat_lerobot.source import files_digest

    before = LeRobotSource(root, REPO).fingerprint
    plain = files_digest(root, "depth/left")
    (root / "depth" / "left" / "README.txt").write_text("depth of the left camera, from the RealSense\n")
    (root / "depth" / "left" / "notes").mkdir()
    (root / "depth" / "left" / "notes" / "episode_000000.safetensors").write_bytes(b"not a sidecar of the folder")
    assert files_digest(root, "depth/left") == plain
    assert LeRobotSource(root, REPO).fingerprint == before == LeRobotSource(recorded, REPO).fingerprint
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
    from gensplat_transforms.cache import GaussianCache

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
        return GaussianCache(tmp_path, RGBDReconstructor(), source.fingerprint)

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
