"""A rig of one external camera: its pivot on the camera's axis at the scene's median depth,
reconstruction from that view alone, the worker and batch paths alike, and the LeRobot
commands (cache, preview, lerobot-train with the one line) on a dataset with one camera."""

from __future__ import annotations

import json
import os
import re
import shutil

import pytest
import torch
from torch.utils.data import default_collate

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache, scene_depth
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.cameras import look_at
from gensplat_transforms.data.scenes import default_cameras
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform
from gensplat_transforms.views.perturbation import Perturbation, move_rig, rig_pivot

LEFT, RIGHT = "observation.images.left", "observation.images.right"


class LeftOnly:
    """The procedural episodes seen by their left camera alone."""

    camera_names = ("left",)

    def __init__(self, source: SceneEpisodes) -> None:
        self.source, self.fingerprint = source, source.fingerprint + "-left"

    def num_frames(self, episode: int) -> int:
        return self.source.num_frames(episode)

    def views(self, episode: int, frame: int) -> Views:
        v = self.source.views(episode, frame)
        return Views(v.images[:1], v.cameras[:1], v.depths[:1])


@pytest.fixture(scope="module")
def one(tmp_path_factory):
    source = LeftOnly(SceneEpisodes(num_episodes=2, num_frames=4, size=32))
    cache = SceneCache(tmp_path_factory.mktemp("one"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(2), progress=False)
    return source, cache, SceneDataset(source.source)


def test_rig_pivot_of_one_camera_lies_on_its_axis():
    c2w = look_at((1.0, 0.5, 0.5), (0.0, 0.0, 0.0))
    pivot = rig_pivot(c2w[None], pivot_depth=1.5)
    torch.testing.assert_close(pivot - c2w[:3, 3], 1.5 * c2w[:3, 2])
    batch = torch.stack([c2w, c2w])[:, None]  # (2, V=1, 4, 4): one pivot per rig
    assert rig_pivot(batch, 1.5).shape == (2, 3)
    for bad in (None, 0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match=r"^rig_pivot: pivot_depth must be a positive distance .* one external"):
            rig_pivot(c2w[None], bad)


def test_a_move_of_one_camera_turns_it_about_its_pivot():
    cams = default_cameras(16, 16)[:1]
    p = Perturbation("y", theta_deg=20.0, mu_m=0.0)
    moved = p.move(cams, 0, pivot_depth=0.8)
    pivot = rig_pivot(cams.c2w, 0.8)
    # the rotation keeps the distance to the pivot and the pivot on the optical axis
    torch.testing.assert_close((moved.c2w[0, :3, 3] - pivot).norm(), torch.tensor(0.8, dtype=torch.float64))
    along = (pivot - moved.c2w[0, :3, 3]) @ moved.c2w[0, :3, 2]
    torch.testing.assert_close(along, torch.tensor(0.8, dtype=torch.float64))
    with pytest.raises(ValueError, match="pivot_depth"):
        p.move(cams, 0)


def test_a_move_about_the_camera_needs_no_pivot():
    cams = default_cameras(16, 16)[:1]
    tilt = Perturbation((0.6, 0.0, 0.8), theta_deg=7.0, shift_m=(0.01, 0.0, -0.02), about="camera")
    moved = tilt.move(cams, 0)  # no pivot_depth: the turn is about the camera's own centre
    torch.testing.assert_close(moved.c2w, tilt.move(cams, 0, pivot_depth=0.8).c2w, rtol=0, atol=1e-12)
    torch.testing.assert_close(moved.c2w[0, :3, 3], cams.c2w[0, :3, 3] + torch.tensor(tilt.shift_m, dtype=torch.float64))
    rows = torch.tensor([[tilt.as_row()], [Perturbation("y", 0.0, about="camera").as_row()]], dtype=torch.float64)
    assert move_rig(torch.stack([cams.c2w, cams.c2w]), rows, [0]).shape == (2, 1, 4, 4)
    for bad in (0.0, -1.0, float("nan")):  # a given pivot_depth is still checked
        with pytest.raises(ValueError, match="pivot_depth must be a positive distance"):
            tilt.move(cams, 0, pivot_depth=bad)
    mixed = torch.tensor([tilt.as_row(), Perturbation("y", 5.0).as_row()], dtype=torch.float64)
    with pytest.raises(ValueError, match="pivot_depth"):  # a move about the pivot needs it
        move_rig(cams.c2w, mixed, [0, 0])


def test_config_and_transform_check_the_pivot_depth(one):
    _, cache, _ = one
    for bad in (0.0, -2.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="GenSplatConfig.pivot_depth"):
            GenSplatConfig(cameras=("left",), pivot_depth=bad)
    with pytest.raises(ValueError, match="needs a calibrated|at least one external camera"):
        GenSplatConfig(cameras=())
    for sampler in ("paper", "arc", "mix", "tilt,arc"):  # moves about the pivot
        with pytest.raises(ValueError, match=r"one reconstructed camera \(left\) needs GenSplatConfig.pivot_depth"):
            GenSplatTransform(GenSplatConfig(cameras=("left",), sampler=sampler), cache)


def test_scene_depth_is_the_median_depth_on_the_axis(one):
    source, _, _ = one
    depth = scene_depth(RGBDReconstructor(), source, range(2))
    truth = torch.stack([source.views(e, f).depths[0, 0].flatten() for e in range(2) for f in (0, 2)])
    # discs sit at their pixel's depth: their distance along the axis is that depth
    assert abs(depth - float(truth.median(1).values.median())) < 0.02


@pytest.mark.parametrize("settings", [{"pivot_depth": 0.9, "level": "large"},
                                      {"sampler": "tilt"}])  # tilts turn about the camera: no pivot_depth
def test_one_camera_worker_and_batch_paths_render_the_same(one, settings):
    _, cache, ds = one
    items = [ds[i] for i in range(6)]
    cfg = GenSplatConfig(cameras=("left",), probability=1.0, report=True, **settings)
    worker = GenSplatTransform(cfg, cache)
    batch = GenSplatTransform(GenSplatConfig(**{**cfg.to_dict(), "render_in": "batch"}), cache)
    torch.manual_seed(3)
    expected = default_collate([worker(item) for item in items])
    torch.manual_seed(3)
    got = render_batch(default_collate([batch(item) for item in items]), batch)
    torch.testing.assert_close(got[LEFT], expected[LEFT], atol=1e-5, rtol=0)
    originals = torch.stack([item[LEFT] for item in items])
    assert (expected[LEFT] - originals).abs().amax((1, 2, 3)).min() > 0.1  # every view moved
    assert torch.equal(expected[RIGHT], torch.stack([item[RIGHT] for item in items]))  # not reconstructed
    assert torch.isfinite(expected[LEFT]).all()


# --------------------------------------------------------------------------- LeRobot
pytest.importorskip("lerobot", reason="the LeRobot commands need the lerobot extra")
REPO = "local/one_camera"


@pytest.fixture(scope="module")
def one_camera_dataset(scene_dataset, tmp_path_factory):
    """A procedural dataset whose only calibrated external camera with depth is ``left``
    (``right`` carries no calibration, ``front`` no depth)."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    root = shutil.copytree(scene_dataset(REPO, episodes=2, frames=20, size=48), tmp_path_factory.mktemp("onecam") / "ds")
    info_path = root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    info["features"][RIGHT]["info"] = {}
    info_path.write_text(json.dumps(info))
    return root


def test_cache_preview_and_lerobot_train_with_one_camera(one_camera_dataset, tmp_path, capsys):
    from gensplat_cli import main
    from helpers import train_diffusion

    root = one_camera_dataset
    assert main(["cache", "--root", str(root), "--repo-id", REPO, "--probability", "1"]) == 0
    settings = json.loads((root / "gensplat" / "config.json").read_text())["transform"]
    assert settings["cameras"] == ["left"] and 0.5 < settings["pivot_depth"] < 1.5
    assert main(["preview", "--root", str(root), "--repo-id", REPO, "--out", str(tmp_path / "p"), "--draws", "1"]) == 0
    assert (tmp_path / "p" / "preview.png").stat().st_size > 0
    capsys.readouterr()
    run = train_diffusion(f"--dataset.repo_id={REPO}", f"--dataset.root={root}", f"--output_dir={tmp_path / 'out'}",
                          "--steps=2", "--batch_size=2", "--num_workers=1", "--save_freq=2", "--log_freq=1")  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    log = run.stderr + run.stdout
    assert "cameras replaced: left (reconstructed from left)" in log
    steps = re.findall(r"GenSplat step \d+: (\d+) of (\d+) samples augmented", log)
    assert steps and all(int(a) == int(n) > 0 for a, n in steps)
