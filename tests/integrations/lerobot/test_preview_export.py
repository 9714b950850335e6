"""``gensplat preview`` and ``gensplat export-ply`` on a small recorded LeRobot dataset."""

import os
import re
import shutil
from dataclasses import replace

import pytest
import torch
from PIL import Image

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
os.environ["HF_HUB_OFFLINE"] = "1"

import av
from gensplat_cli import main
from gensplat_lerobot import LeRobotSource, enable_gensplat, load_settings, save_settings
from gensplat_lerobot.dataset import dataset_cache
from gensplat_lerobot.export import timestep_gaussians
from gensplat_lerobot.training_preview import MIN_TILE_HEIGHT, open_dataset, write_lerobot_preview

from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.geometry import make_reconstructor

REPO = "local/preview_scene"
SIZE, FRAMES = 32, 6
CAMERAS = ("left", "right", "front")  # left and right external with depth; front seen by the policy as is


@pytest.fixture(scope="module")
def cached(scene_dataset, tmp_path_factory):
    """Two 6-frame episodes at 32x32, settings and cache by ``gensplat cache`` (probability 1)."""
    root = tmp_path_factory.mktemp("preview") / "ds"
    shutil.copytree(scene_dataset(REPO, episodes=2, frames=FRAMES, size=SIZE), root)
    main(["cache", "--root", str(root), "--repo-id", REPO, "--probability", "1", "--level", "large"])
    return root


def dataset_files(root):
    """Every file of the dataset outside ``gensplat/`` with its size and modification time."""
    return {(str(f.relative_to(root)), f.stat().st_size, f.stat().st_mtime_ns)
            for f in root.rglob("*") if f.is_file() and f.relative_to(root).parts[0] != "gensplat"}  # fmt: skip


def test_preview_writes_grid_and_video_twice_without_touching_the_dataset(cached, tmp_path, capsys):
    before = dataset_files(cached)
    out = tmp_path / "out"
    args = ["preview", "--root", str(cached), "--repo-id", REPO, "--episode", "1", "--frames", "0", "5",
            "--draws", "2", "--image-transforms", "--out", str(out)]  # fmt: skip
    for _ in range(2):  # a second run into the existing folder replaces the files
        assert main(args) == 0
        assert "preview.png" in capsys.readouterr().out
    assert dataset_files(cached) == before
    scale = -(-MIN_TILE_HEIGHT // SIZE)
    png = Image.open(out / "preview.png")
    assert png.height > 4 * SIZE * scale  # 2 frames x 2 draws
    assert png.width > 2 * len(CAMERAS) * SIZE * scale  # original and policy input per camera
    with av.open(str(out / "preview.mp4")) as video:
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(video=0)]
    assert len(frames) == FRAMES  # every frame of the episode
    assert {f.shape for f in frames} == {(SIZE, 2 * len(CAMERAS) * SIZE, 3)}


def test_preview_items_are_what_enable_gensplat_gives_for_the_same_draws(cached, tmp_path):
    preview = write_lerobot_preview(cached, REPO, tmp_path, episode=1, frames=[2, 4], draws=3,
                                    image_transforms=True, seed=7)  # fmt: skip
    assert preview.indices == [FRAMES + 2] * 3 + [FRAMES + 4] * 3
    plain = open_dataset(cached, REPO)  # no GenSplat, no 2D transforms
    torch.manual_seed(7)
    dataset = enable_gensplat(open_dataset(cached, REPO, image_transforms=True))  # the settings on disk
    changed = set()
    for draw, (index, item) in enumerate(zip(preview.indices, preview.items)):
        assert item["gensplat.applied"].all()  # forced on
        ref = dataset.augmented(index, view=draw % 3)
        for name in CAMERAS:
            key = f"observation.images.{name}"
            assert torch.equal(item[key], ref[key])
            if not torch.equal(item[key], plain[index][key]):
                changed.add(name)
    assert changed == set(CAMERAS)  # rendered and 2D-transformed, the front camera by the 2D transforms
    # a frame's rows show the episode's three views: three distinct moves
    moves = {tuple(item["gensplat.move"].flatten().tolist()) for item in preview.items[:3]}
    assert len(moves) == 3 and moves == {tuple(item["gensplat.move"].flatten().tolist()) for item in preview.items[3:]}
    with pytest.raises(ValueError, match=r"view must be an integer in 0..2"):
        dataset.augmented(preview.indices[0], view=3)


def test_preview_renders_in_the_item_whatever_the_settings_say(cached, tmp_path):
    root = tmp_path / "ds"
    shutil.copytree(cached, root)
    config, reconstructor = load_settings(root)
    save_settings(root, replace(config, render_in="batch"), reconstructor)  # rendered after collation in training
    batch = write_lerobot_preview(root, REPO, tmp_path / "batch", frames=[1], draws=1)
    worker = write_lerobot_preview(cached, REPO, tmp_path / "worker", frames=[1], draws=1)
    key = "observation.images.left"
    assert torch.equal(batch.items[0][key], worker.items[0][key])
    assert not torch.equal(batch.items[0][key], open_dataset(root, REPO)[batch.indices[0]][key])


def test_preview_refuses_an_output_folder_inside_the_dataset(cached):
    with pytest.raises(ValueError, match="inside the dataset"):
        write_lerobot_preview(cached, REPO, cached / "preview")
    assert not (cached / "preview").exists()


def test_export_ply_round_trips_to_the_cached_gaussians(cached, tmp_path, capsys):
    root = tmp_path / "ds"
    shutil.copytree(cached, root)
    shutil.rmtree(root / "gensplat" / "cache")  # settings kept: the episode is built first
    out = tmp_path / "ply" / "timestep.ply"
    assert main(["export-ply", "--root", str(root), "--repo-id", REPO, "--episode", "1", "--frame", "3",
                 "--out", str(out)]) == 0  # fmt: skip
    assert str(out) in capsys.readouterr().out
    config, spec = load_settings(root)
    source = LeRobotSource(root, REPO, config.cameras)
    cache = dataset_cache(root, make_reconstructor(spec), source)
    assert cache.status(1) == "ok" and cache.status(0) == "missing"
    want = cache.read(1, 3, source.views(1, 3).images).gaussians
    got = Gaussians.from_ply(out)
    assert len(got) == len(want) > 0
    for field in ("means", "scales", "quats", "opacities", "sh"):
        torch.testing.assert_close(getattr(got, field), getattr(want, field), rtol=1e-5, atol=1e-5)
    other = timestep_gaussians(root, REPO, 1, 4)  # another timestep: other Gaussians
    assert len(other) != len(got) or not torch.equal(other.means, got.means)


@pytest.mark.parametrize(
    ("command", "message"),
    [
        (["export-ply", "--episode", "2", "--frame", "0"], r"episode 2 is not in the dataset, which has episodes 0\.\.1"),
        (["export-ply", "--episode", "1", "--frame", "6"], r"frame\(s\) \[6\] not in episode 1, which has frames 0\.\.5"),
        (["export-ply", "--episode", "-1", "--frame", "0"], r"episode -1 is not in the dataset"),
        (["preview", "--episode", "1", "--frames", "0", "9"], r"frame\(s\) \[9\] not in episode 1"),
        (["preview", "--episode", "5"], r"episode 5 is not in the dataset"),
    ],
)
def test_bad_episode_or_frame_is_a_clear_error(cached, tmp_path, capsys, command, message):
    out = ["--out", str(tmp_path / ("x.ply" if command[0] == "export-ply" else "p"))]
    assert main([command[0], "--root", str(cached), "--repo-id", REPO, *command[1:], *out]) == 2
    assert re.search(f"^gensplat: error: {message}", capsys.readouterr().err)
    assert not list(tmp_path.iterdir())  # nothing written


def test_preview_labels_name_each_move_and_where_it_turns():
    from gensplat_lerobot.training_preview import _label

    from gensplat_transforms.views.perturbation import Perturbation

    moves = [Perturbation("x", 5.0, 0.02), Perturbation((0.0, 0.6, 0.8), -7.5, shift_m=(0.01, 0, 0), about="camera"),
             Perturbation("z", 30.0, focal_scale=1.2)]  # fmt: skip
    item = {"gensplat.axis": torch.tensor([0, -1, 2]), "gensplat.move": torch.tensor([m.as_row() for m in moves])}
    label = _label(item, frame=3, view=0, cameras=("left", "right", "top"))
    assert label.splitlines()[:3] == ["frame 3, view 1", "left: x +5.0 deg", "  mu 2.0 cm"]
    assert "right: -7.5 deg\n  about +0.0,+0.6,+0.8\n  through the camera\n  mu 0.0 cm\n  shift +1.0,+0.0,+0.0 cm" in label
    assert label.count("through the camera") == 1 and label.endswith("top: z +30.0 deg\n  mu 0.0 cm\n  focal x1.2")


@pytest.mark.parametrize(("scale", "text"), [(0.8123, "0.812"), (1e-3, "0.001"), (999.7, "1e+03")])
def test_preview_labels_give_any_focal_change_in_three_digits(scale, text):
    from gensplat_lerobot.training_preview import _label

    from gensplat_transforms.views.perturbation import Perturbation

    item = {"gensplat.axis": torch.tensor([0]), "gensplat.move": torch.tensor([Perturbation(focal_scale=scale).as_row()],
                                                                                 dtype=torch.float64)}  # fmt: skip
    assert _label(item, frame=0, view=0, cameras=("left",)).endswith(f"focal x{text}")
