"""Nothing a user types as an output path harms the dataset: every command's ``--out`` is checked
(gensplat_transforms.data.outputs), refused ones end as ``gensplat: error:`` lines, and ``gensplat
record`` refuses bad sizes up front and leaves no partial dataset when it fails."""

import hashlib
import os
import shutil
import stat

import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
os.environ["HF_HUB_OFFLINE"] = "1"

import gensplat_sim.record as sim_record
from gensplat_cli import main
from gensplat_sim.world import WorldConfig

from gensplat_transforms.core.gaussians import Gaussians

REPO = "local/outputs_scene"


@pytest.fixture(scope="module")
def cached(scene_dataset, tmp_path_factory):
    """One 3-frame episode at 32x32 with gensplat cache's settings and cache."""
    root = tmp_path_factory.mktemp("outputs") / "ds"
    shutil.copytree(scene_dataset(REPO, episodes=1, frames=3, size=32), root)
    assert main(["cache", "--root", str(root), "--repo-id", REPO]) == 0
    return root


def dataset_hashes(root):
    """sha256 of every file under ``root`` outside ``gensplat/``."""
    return {str(f.relative_to(root)): hashlib.sha256(f.read_bytes()).hexdigest()
            for f in root.rglob("*") if f.is_file() and f.relative_to(root).parts[0] != "gensplat"}  # fmt: skip


def refused(capsys, args, message="") -> str:
    """Run ``gensplat <args>``: exit status 2 and a ``gensplat: error:`` line naming ``message``."""
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("gensplat: error: ") and message in err and "Traceback" not in err
    return err


def into_dataset(root, tmp_path, how: str):
    """An output path that leads into the dataset: ``inside`` it, a ``link`` (a symbolic link to a
    dataset file) or a path ``through`` a linked parent folder."""
    if how == "inside":
        return root / "meta" / "info.json"
    if how == "link":
        (tmp_path / "link").symlink_to(root / "meta" / "info.json")
        return tmp_path / "link"
    (tmp_path / "parent").symlink_to(root / "meta")
    return tmp_path / "parent" / "info.json"


def ply_args(root, out):
    return ["export-ply", "--root", str(root), "--repo-id", REPO, "--episode", "0", "--frame", "1", "--out", str(out)]


@pytest.mark.parametrize("how", ["inside", "link", "through"])
def test_export_ply_into_the_dataset_is_refused(cached, tmp_path, capsys, how):
    before = dataset_hashes(cached)
    out = into_dataset(cached, tmp_path, how)
    err = refused(capsys, ply_args(cached, out), "inside the dataset")
    assert str(cached) in err
    assert dataset_hashes(cached) == before
    assert how != "link" or out.is_symlink()


@pytest.mark.parametrize("how", ["inside", "link", "through"])
def test_preview_into_the_dataset_is_refused(cached, tmp_path, capsys, how):
    before = dataset_hashes(cached)
    out = tmp_path / "out"
    if how == "inside":
        out = cached / "preview"
    elif how == "link":  # an earlier preview.png replaced by a link into the dataset
        out.mkdir()
        (out / "preview.png").symlink_to(cached / "meta" / "info.json")
    else:
        (tmp_path / "parent").symlink_to(cached)
        out = tmp_path / "parent" / "preview"
    refused(capsys, ["preview", "--root", str(cached), "--repo-id", REPO, "--draws", "1", "--out", str(out)],
            "inside the dataset")  # fmt: skip
    assert dataset_hashes(cached) == before
    assert not (cached / "preview").exists()


def test_train_model_into_the_dataset_is_refused(cached, tmp_path, capsys):
    before = dataset_hashes(cached)
    train = ["train-model", "--steps", "1", "--data", "lerobot", "--root", str(cached), "--repo-id", REPO]
    refused(capsys, [*train, "--out", str(cached / "run")], "inside the dataset")
    out = tmp_path / "run"
    out.mkdir()
    (out / "log.jsonl").symlink_to(cached / "meta" / "info.json")  # the log is appended to
    refused(capsys, [*train, "--out", str(out)], "inside the dataset")
    assert dataset_hashes(cached) == before
    assert not (cached / "run").exists()


def test_gensplat_folder_linked_to_another_disk_keeps_working(cached, tmp_path, capsys):
    root, elsewhere = tmp_path / "ds", tmp_path / "other_disk"
    shutil.copytree(cached, root)
    shutil.move(root / "gensplat", elsewhere)
    (root / "gensplat").symlink_to(elsewhere)
    before = dataset_hashes(root)
    assert main(["cache", "--root", str(root), "--repo-id", REPO]) == 0
    assert "(1 already valid)" in capsys.readouterr().out  # its links to the dataset's depth still lead there
    assert main(ply_args(root, root / "gensplat" / "t.ply")) == 0
    assert len(Gaussians.from_ply(elsewhere / "t.ply")) > 0
    assert dataset_hashes(root) == before
    capsys.readouterr()
    (root / "gensplat" / "escape").symlink_to(root / "meta")  # out of gensplat/ into the dataset
    refused(capsys, ply_args(root, root / "gensplat" / "escape" / "info.json"), "inside the dataset")
    assert dataset_hashes(root) == before


def test_gensplat_folder_linked_into_the_dataset_is_refused(cached, tmp_path, capsys):
    """``<root>/gensplat`` a link to one of the dataset's own folders: cache, calibrate and the
    estimate write nothing there."""
    root = tmp_path / "ds"
    shutil.copytree(cached, root, ignore=shutil.ignore_patterns("gensplat"))
    (root / "gensplat").symlink_to(root / "meta")
    before = {p.name for p in (root / "meta").iterdir()}, dataset_hashes(root)
    refused(capsys, ["cache", "--root", str(root), "--repo-id", REPO], "inside the dataset")
    assert ({p.name for p in (root / "meta").iterdir()}, dataset_hashes(root)) == before
    calibration = tmp_path / "calibration.json"
    calibration.write_text('{"left": {"fx": 30, "fy": 30, "cx": 16, "cy": 16, "c2w": '
                           '[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}}')
    info = root / "meta" / "info.json"
    info.write_text(info.read_text().replace('"camera.intrinsics"', '"was.intrinsics"'))  # left uncalibrated
    before = {p.name for p in (root / "meta").iterdir()}, dataset_hashes(root)
    refused(capsys, ["calibrate", "from-file", "--root", str(root), str(calibration)], "inside the dataset")
    assert ({p.name for p in (root / "meta").iterdir()}, dataset_hashes(root)) == before


def test_a_folder_for_a_file_or_a_file_for_a_folder_is_a_clear_error(cached, tmp_path, capsys):
    a_file = tmp_path / "file.txt"
    a_file.write_text("mine")
    (tmp_path / "p").mkdir()
    (tmp_path / "p" / "preview.png").mkdir()
    preview = ["preview", "--root", str(cached), "--repo-id", REPO, "--draws", "1", "--out"]
    refused(capsys, ply_args(cached, tmp_path), "is a folder")
    refused(capsys, ply_args(cached, a_file / "t.ply"), "is a file, not a folder")
    refused(capsys, [*preview, str(a_file)], "is a file, not a folder")
    refused(capsys, [*preview, str(tmp_path / "p")], "is a folder")
    refused(capsys, ["train-model", "--steps", "1", "--out", str(a_file)], "is a file, not a folder")
    refused(capsys, ["demo", "--out", str(a_file)], "is a file, not a folder")
    refused(capsys, ["record", "--out", str(a_file / "ds")], "is a file, not a folder")
    assert a_file.read_text() == "mine"



def test_a_device_or_pipe_for_a_file_is_refused_not_replaced(cached, tmp_path, capsys):
    """``--out /dev/null`` (run as root) replaced the device with a regular file: an output that
    is not a regular file is refused and stays what it is; here a named pipe stands in for it."""
    pipe = tmp_path / "pipe.ply"
    os.mkfifo(pipe)
    refused(capsys, ply_args(cached, pipe), "is not a regular file (a device, a pipe or a socket)")
    (tmp_path / "p").mkdir()
    os.mkfifo(tmp_path / "p" / "preview.mp4")
    refused(capsys, ["preview", "--root", str(cached), "--repo-id", REPO, "--draws", "1", "--out",
                     str(tmp_path / "p")], "is not a regular file")  # fmt: skip
    assert stat.S_ISFIFO(os.lstat(pipe).st_mode) and stat.S_ISFIFO(os.lstat(tmp_path / "p" / "preview.mp4").st_mode)

@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--size", "24"], "at least 32 px per side for MP4 video"),  # the video encoder would crash the process
        (["--size", "64", "--width", "16"], "image width 16 px"),
        (["--width", "0", "--images"], "image width 0 px"),  # never silently replaced by --size
        (["--height", "-3", "--images"], "image height -3 px"),
        (["--size", "1", "--images"], "at least 2 px per side for PNG images"),
        (["--fps", "0"], "fps 0"),
        (["--fps", "1000"], "fps 1000"),
        (["--episodes", "0"], "episodes 0"),
    ],
    ids=["video-24", "video-width-16", "width-0", "height-negative", "png-1", "fps-0", "fps-1000", "episodes-0"],
)
def test_record_refuses_bad_sizes_up_front(tmp_path, capsys, options, message):
    refused(capsys, ["record", "--out", str(tmp_path / "ds"), *options], message)
    assert not (tmp_path / "ds").exists()


def test_record_refuses_an_existing_folder(tmp_path, capsys):
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "mine").write_text("kept")
    refused(capsys, ["record", "--out", str(tmp_path / "ds")], "already exists")
    assert (tmp_path / "ds" / "mine").read_text() == "kept"


@pytest.mark.parametrize("failure", [KeyboardInterrupt, RuntimeError])
def test_record_leaves_no_partial_dataset_when_it_fails(tmp_path, monkeypatch, failure):
    written = []

    def fail(root, *args):  # after the first episode's video is encoded
        written.extend(p.name for p in root.iterdir())
        raise failure("stopped")

    monkeypatch.setattr(sim_record, "save_sim_episode", fail)
    config = sim_record.RecordConfig(tmp_path / "ds", episodes=2, max_frames=2, world=WorldConfig(height=32, width=32))
    with pytest.raises(failure):
        sim_record.record(config, progress=False)
    assert {"meta", "videos"} <= set(written)
    assert not (tmp_path / "ds").exists()


def dataset_snapshot(root):
    """Every entry under ``root`` outside ``gensplat/``, links not followed: {relative path:
    sha256 of a file, the target of a link, or "dir"}."""
    out = {}
    for folder, dirs, files in os.walk(root):
        rel = os.path.relpath(folder, root)
        if rel.split(os.sep)[0] == "gensplat":
            continue
        for name in dirs + files:
            path = os.path.join(folder, name)
            key = os.path.normpath(os.path.join(rel, name))
            if os.path.islink(path):
                out[key] = "-> " + os.readlink(path)
            elif os.path.isdir(path):
                out[key] = "dir"
            else:
                with open(path, "rb") as f:
                    out[key] = hashlib.sha256(f.read()).hexdigest()
    return out


@pytest.mark.parametrize("linked", ["cache", "cache/id"])
@pytest.mark.parametrize("target", ["meta", "data"])
def test_cache_folders_linked_into_the_dataset_are_refused(cached, tmp_path, capsys, linked, target):
    """``<root>/gensplat/cache`` (or the cache of one reconstructor) a link to one of the dataset's
    own folders: ``gensplat cache`` refuses it and no byte of the dataset changes."""
    root = tmp_path / "ds"
    shutil.copytree(cached, root, ignore=shutil.ignore_patterns("cache"))
    if linked == "cache":
        (root / "gensplat" / "cache").symlink_to(root / target)
    else:
        (identity,) = [p.name for p in (cached / "gensplat" / "cache").iterdir() if p.is_dir()]
        (root / "gensplat" / "cache").mkdir()
        (root / "gensplat" / "cache" / identity).symlink_to(root / target)
    before = dataset_snapshot(root)
    err = refused(capsys, ["cache", "--root", str(root), "--repo-id", REPO], "outside GenSplat's folder")
    assert "symbolic link" in err
    assert dataset_snapshot(root) == before
    refused(capsys, ply_args(root, tmp_path / "t.ply"), "outside GenSplat's folder")  # reading it too
    assert dataset_snapshot(root) == before


def test_a_link_where_the_cache_keeps_a_lock_file_is_refused(cached, tmp_path, capsys):
    """A dangling link in place of an episode's lock file: opening the lock created the link's
    target, a new file in the dataset's meta/ folder."""
    root = tmp_path / "ds"
    shutil.copytree(cached, root)
    (folder,) = (root / "gensplat" / "cache").iterdir()
    (folder / "episode_000000.safetensors").unlink()
    (folder / ".episode_000000.lock").unlink(missing_ok=True)
    (folder / ".episode_000000.lock").symlink_to(root / "meta" / "new_file")
    before = dataset_snapshot(root)
    assert main(["cache", "--root", str(root), "--repo-id", REPO]) == 2
    err = capsys.readouterr().err  # after the progress bars
    assert err.splitlines()[-1].endswith("is a symbolic link where GenSplat keeps a lock file: remove it"), err
    assert dataset_snapshot(root) == before and not os.path.lexists(root / "meta" / "new_file")


@pytest.mark.parametrize("owned", ["calibration.json", "config.json", "dataset.json", "cache/x.ply"])
def test_outputs_never_replace_gensplat_s_own_files(cached, tmp_path, capsys, owned):
    root = tmp_path / "ds"
    shutil.copytree(cached, root)
    before = {p: p.read_bytes() for p in (root / "gensplat").glob("*.json")}
    refused(capsys, ply_args(root, root / "gensplat" / owned), "GenSplat's own")
    (tmp_path / "own").symlink_to(root / "gensplat")  # the same files through a link
    refused(capsys, ply_args(root, tmp_path / "own" / owned), "GenSplat's own")
    refused(capsys, ["preview", "--root", str(root), "--repo-id", REPO, "--draws", "1", "--out",
                     str(root / "gensplat" / "cache")], "GenSplat's own")  # fmt: skip
    assert {p: p.read_bytes() for p in (root / "gensplat").glob("*.json")} == before
    assert main(ply_args(root, root / "gensplat" / "t.ply")) == 0  # a file of the user's own stays allowed


def test_every_file_gensplat_keeps_is_listed_as_its_own(tmp_path):
    from gensplat_lerobot.dataset import content_path, settings_path

    from gensplat_transforms.data.format import GENSPLAT_OWNED, calibration_path, digests_path

    for path in (f(tmp_path) for f in (content_path, settings_path, calibration_path, digests_path)):
        assert path.parent == tmp_path / "gensplat" and path.name in GENSPLAT_OWNED


@pytest.mark.parametrize("args, message", [
    (["cache", "--sampler", "tilt", "--shift-m", "1000"], "GenSplatConfig.shift_m: a camera moves at most 1 m"),
    (["cache", "--pivot-depth", "1e300"], "GenSplatConfig.pivot_depth: a positive distance in metres, at most 100"),
    (["cache", "--sampler", "arc", "--pivot-depth", "1e6"], "at most 100"),
    (["cache", "--views-per-source", str(2**40)], "views_per_source must be in 1..1000"),
    (["preview", "--draws", "1000000000"], "draws must be in 1..32"),
])  # fmt: skip
def test_settings_that_render_no_picture_are_refused_at_the_command(cached, tmp_path, capsys, args, message):
    """The command refuses them in one line, before the settings in place are replaced."""
    root = tmp_path / "ds"
    shutil.copytree(cached, root)
    settings = (root / "gensplat" / "config.json").read_bytes()
    out = ["--out", str(tmp_path / "preview")] if args[0] == "preview" else []
    refused(capsys, [args[0], "--root", str(root), "--repo-id", REPO, *args[1:], *out], message)
    assert (root / "gensplat" / "config.json").read_bytes() == settings


@pytest.mark.parametrize("where", ["cache", "cache/id"])
def test_a_file_where_the_cache_folder_belongs_is_a_clear_error(cached, tmp_path, capsys, where):
    root = tmp_path / "ds"
    shutil.copytree(cached, root, ignore=shutil.ignore_patterns("cache"))
    if where == "cache":
        (root / "gensplat" / "cache").write_text("a note")
    else:
        (identity,) = [p.name for p in (cached / "gensplat" / "cache").iterdir() if p.is_dir()]
        (root / "gensplat" / "cache").mkdir()
        (root / "gensplat" / "cache" / identity).write_text("a note")
    refused(capsys, ["cache", "--root", str(root), "--repo-id", REPO], "is a file, not a folder")


@pytest.mark.parametrize("owned", ["config.json", "dataset.json", "cache/{identity}/episode_000000.safetensors"])
def test_a_folder_where_gensplat_keeps_a_file_is_a_clear_error(cached, tmp_path, capsys, owned):
    """A folder in the way of one of GenSplat's own files was an IsADirectoryError traceback
    (after the work, at the rename): one line naming it; where the digests' memo goes, a folder
    only costs the memo."""
    root = tmp_path / "ds"
    shutil.copytree(cached, root)
    (identity,) = [p.name for p in (root / "gensplat" / "cache").iterdir()]
    path = root / "gensplat" / owned.format(identity=identity)
    path.unlink()
    path.mkdir()
    for args in (["cache", "--root", str(root), "--repo-id", REPO], ply_args(root, tmp_path / "t.ply")):
        if owned == "dataset.json" and args[0] == "export-ply":
            continue  # export-ply neither reads nor writes it
        assert main(args) == 2
        err = capsys.readouterr().err  # after the progress bars
        assert err.splitlines()[-1].startswith(f"gensplat: error: {path}") and "Traceback" not in err, err
    shutil.rmtree(root / "gensplat")
    shutil.copytree(cached / "gensplat", root / "gensplat")
    (root / "gensplat" / "digests.json").unlink()
    (root / "gensplat" / "digests.json").mkdir()
    assert main(["cache", "--root", str(root), "--repo-id", REPO]) == 0


def test_no_command_changes_a_byte_of_the_dataset(cached, tmp_path, capsys):
    """Every entry outside ``gensplat/``, links included (a link inside the dataset to a file
    elsewhere, whose target is watched too), is the same after each command that reads the
    dataset, whether it succeeds or is refused."""
    root, elsewhere = tmp_path / "ds", tmp_path / "elsewhere.txt"
    shutil.copytree(cached, root, symlinks=True)
    elsewhere.write_text("a file the dataset links to")
    (root / "notes.txt").symlink_to(elsewhere)
    snapshot = lambda: (dataset_snapshot(root), elsewhere.read_bytes())
    before = snapshot()
    commands = [
        ["cache", "--root", str(root), "--repo-id", REPO],
        ["cache", "--root", str(root), "--repo-id", REPO, "--sampler", "tilt", "--probability", "0.5"],
        ["export-ply", "--root", str(root), "--repo-id", REPO, "--episode", "0", "--frame", "1",
         "--out", str(tmp_path / "t.ply")],
        ["preview", "--root", str(root), "--repo-id", REPO, "--draws", "1", "--out", str(tmp_path / "preview")],
        ["export-ply", "--root", str(root), "--repo-id", REPO, "--episode", "0", "--frame", "1",
         "--out", str(root / "notes.txt")],  # refused: through the link
        ["calibrate", "from-file", "--root", str(root), str(tmp_path / "missing.json")],  # refused
    ]  # fmt: skip
    for args in commands:
        main(args)
        capsys.readouterr()
        assert snapshot() == before, args
