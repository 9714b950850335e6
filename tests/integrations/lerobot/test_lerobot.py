"""LeRobot integration: a real local LeRobotDataset, the one-line lerobot-train hook, pi0, and
simulated recordings in LeRobot's default MP4 video at a non-square size."""

import json
import logging
import os
import re
import shutil
from pathlib import Path

import pytest
import torch

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
os.environ["HF_HUB_OFFLINE"] = "1"

from gensplat_lerobot import (
    LeRobotSource,
    LeRobotViews,
    enable_gensplat,
    load_settings,
    prepare,
    save_settings,
    video_backend,
)
from gensplat_lerobot.dataset import dataset_cache, make_reconstructor, settings_path
from gensplat_lerobot.scene_dataset import record_scene_dataset
from helpers import train_diffusion
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from safetensors.torch import save_file

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.cache.store import StaleCacheError
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.data.format import DEPTH_FORMAT, depth_path, load_depth, save_depth
from gensplat_transforms.geometry.model import PATCH_SIZE
from gensplat_transforms.transform import GenSplatConfig
from gensplat_transforms.views.perturbation import PerturbationRange

REPO = "local/gensplat_scene"
SIM_REPO = "gensplat/sim_pick_place"
POLICIES = Path(__file__).resolve().parents[3] / "policies"
LEFT = "observation.images.left"


@pytest.fixture(scope="module")
def recorded(scene_dataset):
    """2 episodes of 20 frames at 48x48, RGB-D (shared: read only)."""
    return scene_dataset(REPO, episodes=2, frames=20, size=48)


@pytest.fixture
def dataset_root(recorded, dataset_copy):
    """A fresh copy of ``recorded``, to change."""
    return dataset_copy(recorded)


def record_and_cache(root: Path, height: int, width: int, frames: int | None = None) -> Path:
    """A simulated pick-and-place episode (the first ``frames`` timesteps, or all) in LeRobot's
    default MP4 video at ``height x width``, its depth cache built by ``gensplat cache`` with
    every sample augmented (probability 1)."""
    import gensplat_sim  # noqa: F401  (selects the headless GL backend before MuJoCo loads)

    pytest.importorskip("mujoco", reason="recording needs the 'sim' extra (mujoco)")
    from gensplat_cli import main
    from gensplat_sim.record import RecordConfig, record
    from gensplat_sim.world import WorldConfig

    scheduling = os.sched_getscheduler(0), os.sched_getparam(0)
    if frames is None:
        main(["record", "--out", str(root), "--episodes", "1", "--height", str(height), "--width", str(width)])
    else:  # a short clip: the command records whole demonstrations
        world = WorldConfig(height=height, width=width)
        record(RecordConfig(root, episodes=1, max_frames=frames, world=world), progress=False)
    # run by root, the AV1 encoder makes its thread real-time: recording gives the old policy back
    assert (os.sched_getscheduler(0), os.sched_getparam(0)) == scheduling
    main(["cache", "--root", str(root), "--repo-id", SIM_REPO, "--probability", "1"])
    return root


@pytest.fixture(scope="module")
def sim_video(tmp_path_factory):
    """A whole simulated episode recorded by ``gensplat record`` at 48x64 (HxW), MP4, cached."""
    return record_and_cache(tmp_path_factory.mktemp("sim") / "ds", 48, 64)


def assert_augmented_at_own_size(root: Path, index: int, height: int, width: int) -> None:
    """The one-line hook replaces the external cameras' images of ``root[index]`` with renders
    at the dataset's own size (no resize) and dtype; the wrist camera is kept."""
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["features"][LEFT]["dtype"] == "video"  # LeRobot's default storage
    plain = LeRobotDataset(SIM_REPO, root=root)
    ds = enable_gensplat(LeRobotDataset(SIM_REPO, root=root))
    assert ds.gensplat.cache.image_size(0) == (width, height)  # rendered at the dataset's size
    item, ref = ds[index], plain[index]
    for cam in ("left", "right"):
        key = f"observation.images.{cam}"
        assert item[key].shape == ref[key].shape == (3, height, width) and item[key].dtype == ref[key].dtype
        # a new view of the same scene: like the original (15-19 dB; a black image: 5 dB) and unlike
        # it beyond the video's coding noise (mean difference 0.06-0.11; the noise: ~0.004)
        assert psnr(item[key], ref[key]) > 12.0
        assert (item[key] - ref[key]).abs().mean() > 0.02
    assert torch.equal(item["observation.images.wrist"], ref["observation.images.wrist"])


def test_video_non_square_recording_is_cached_and_transformed(sim_video):
    assert_augmented_at_own_size(sim_video, 10, 48, 64)


def test_video_480x640_recording_is_cached_and_transformed(tmp_path):
    assert_augmented_at_own_size(record_and_cache(tmp_path / "ds", 480, 640, frames=3), 1, 480, 640)


def test_recorded_dataset_carries_calibration_and_depth(recorded):
    ds = LeRobotDataset(REPO, root=recorded)
    assert ds.num_episodes == 2 and ds.num_frames == 40
    source = LeRobotSource(recorded, REPO)
    assert source.camera_names == ("left", "right")  # the external cameras with depth
    # the cache is found by the content, not by the name the dataset is opened under
    assert LeRobotSource(recorded, "someone/another_name").fingerprint == source.fingerprint
    # the cache stores the cameras in order: another order is another cache
    assert LeRobotSource(recorded, REPO, ("right", "left")).fingerprint != source.fingerprint
    views = source.views(1, 5)
    assert views.depths.shape == (2, 1, 48, 48) and (views.depths > 0).all()
    truth = SceneEpisodes(num_episodes=2, num_frames=20, size=48)
    rgb, depth = truth.render(1, 5)
    torch.testing.assert_close(views.depths, depth[:2], atol=2e-3, rtol=1e-3)  # float16 storage
    assert (views.images - rgb[:2]).abs().max() <= 1 / 255 + 1e-6  # 8-bit images
    torch.testing.assert_close(views.cameras.c2w, truth.cameras.c2w[:2])


def test_settings_round_trip(tmp_path):
    config = GenSplatConfig(cameras=("left", "right"), replace=("left",), level=PerturbationRange((2.0, 4.0), (0.0, 0.0)))
    save_settings(tmp_path, config, {"name": "geometry", "model": "weights"})
    assert load_settings(tmp_path) == (config, {"name": "geometry", "model": "weights"})


@pytest.mark.parametrize("text", ["{", "[]", '{"transform": {}}', '{"transform": {"tilt_deg": "10"}, "reconstructor": {}}',
                                  '{"transform": {"colour": 1}, "reconstructor": {}}', '{"transform": {}, "reconstructor": 3}'])  # fmt: skip
def test_damaged_settings_are_reported_naming_the_file(tmp_path, text):
    save_settings(tmp_path, GenSplatConfig(), {"name": "rgbd"})
    path = settings_path(tmp_path)
    path.write_text(text)
    with pytest.raises(ValueError, match=rf"^{re.escape(str(path))}: not GenSplat settings .*gensplat cache --root"):
        load_settings(tmp_path)


def test_enable_gensplat_renders_external_views_only(dataset_root):
    save_settings(dataset_root, GenSplatConfig(probability=1.0, level="large", report=True), {"name": "rgbd"})
    plain = LeRobotDataset(REPO, root=dataset_root)
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    item, ref = ds[7], plain[7]
    assert item["gensplat.applied"].all()
    for cam in ("left", "right"):
        key = f"observation.images.{cam}"
        assert item[key].shape == ref[key].shape and item[key].dtype == ref[key].dtype
        assert not torch.equal(item[key], ref[key])
    assert torch.equal(item["observation.images.front"], ref["observation.images.front"])
    torch.testing.assert_close(item["action"], ref["action"])  # actions are kept
    # cache was built lazily, beside the dataset; the dataset files were not touched
    assert list((dataset_root / "gensplat" / "cache").rglob("episode_000000.safetensors"))


def test_temporal_stacks_follow_delta_timestamps(dataset_root):
    save_settings(dataset_root, GenSplatConfig(probability=1.0, level="small", views_per_source=1), {"name": "rgbd"})
    dt = {LEFT: [-0.2, -0.1, 0.0]}
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root, delta_timestamps=dt))
    assert ds.gensplat.cfg.frame_offsets == (-2, -1, 0)
    custom = GenSplatConfig(probability=1.0, level=PerturbationRange((2.0, 4.0), (0.01, 0.02)), views_per_source=1)
    ranged = enable_gensplat(LeRobotDataset(REPO, root=dataset_root, delta_timestamps=dt), custom)
    assert ranged.gensplat.cfg.level == custom.level and ranged[5][LEFT].shape == (3, 3, 48, 48)
    single = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    stack = ds[5][LEFT]  # frames 3, 4, 5 of episode 0
    assert stack.shape == (3, 3, 48, 48)
    torch.testing.assert_close(stack[0], single[3][LEFT])
    torch.testing.assert_close(stack[2], single[5][LEFT])
    first = ds[0][LEFT]  # padded at the episode start, like LeRobot does
    torch.testing.assert_close(first[0], first[2])


def test_prepare_builds_cache_and_is_resumable(dataset_root):
    stats = prepare(dataset_root, REPO, GenSplatConfig(), progress=False)
    assert set(stats) == {0, 1} and all(s.num_frames == 20 for s in stats.values())
    assert max(s.bytes_per_timestep for s in stats.values()) < 1e6
    again = prepare(dataset_root, REPO, GenSplatConfig(), progress=False)
    assert all(s is None for s in again.values())


def test_rerecorded_frames_make_the_cache_stale(recorded, dataset_root, scene_dataset):
    source = LeRobotSource(dataset_root, REPO)
    assert source.fingerprint == LeRobotSource(recorded, REPO).fingerprint  # a copy is the same data
    prepare(dataset_root, REPO, GenSplatConfig(), episodes=[0], progress=False)
    reconstructor = make_reconstructor(load_settings(dataset_root)[1])
    assert dataset_cache(dataset_root, reconstructor, source).status(0) == "ok"
    # same episode and frame counts, other frames: info.json alone cannot tell
    other = scene_dataset(REPO, episodes=2, frames=20, size=48, seed=7)
    for d in ("data", "depth"):
        shutil.rmtree(dataset_root / d)
        shutil.copytree(other / d, dataset_root / d)
    rerecorded = LeRobotSource(dataset_root, REPO)
    assert rerecorded.fingerprint != source.fingerprint
    assert dataset_cache(dataset_root, reconstructor, rerecorded).status(0) == "stale"
    # a depth sidecar saved again with other values
    save_depth(dataset_root, "left", 1, load_depth(dataset_root, "left", 1)[:, 0] + 0.01)
    assert LeRobotSource(dataset_root, REPO).fingerprint != rerecorded.fingerprint


def cache_files(root: Path) -> dict[Path, tuple[int, int]]:
    """(inode, mtime in ns) of every episode file of the dataset's cache: any rebuild changes them."""
    return {f: (f.stat().st_ino, f.stat().st_mtime_ns) for f in (root / "gensplat" / "cache").rglob("*.safetensors")}


def gensplat_warnings(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.name.startswith("gensplat") and r.levelno >= logging.WARNING]


def test_another_repo_id_uses_the_cache_as_it_is(dataset_root, caplog):
    """A dataset opened under another repo id than ``gensplat cache`` was given (a typo, or the
    demo's id against a policy config's) trains from the same cache: nothing rebuilt, no warning."""
    prepare(dataset_root, REPO, GenSplatConfig(probability=1.0, report=True), progress=False)
    before = cache_files(dataset_root)
    assert len(before) == 2
    with caplog.at_level(logging.INFO):
        ds = enable_gensplat(LeRobotDataset("someone/tpyo", root=dataset_root))
        items = [ds[3], ds[25]]  # one frame of each episode
    assert ds.gensplat_cached == (2, 2)
    assert all(item["gensplat.applied"].all() for item in items)
    assert cache_files(dataset_root) == before
    assert gensplat_warnings(caplog) == []


def test_changed_dataset_stops_with_what_differs(dataset_root):
    prepare(dataset_root, REPO, GenSplatConfig(), progress=False)
    before = cache_files(dataset_root)
    save_depth(dataset_root, "left", 1, load_depth(dataset_root, "left", 1)[:, 0] + 0.01)  # re-measured depth
    command = f"gensplat cache --root {dataset_root} --repo-id other/name"
    with pytest.raises(StaleCacheError, match=rf"changed since .*\(the files under depth/left/\): run `{re.escape(command)}`"):
        enable_gensplat(LeRobotDataset("other/name", root=dataset_root))
    assert cache_files(dataset_root) == before  # not rebuilt either


def test_missing_episodes_are_announced_with_the_command(dataset_root, caplog):
    prepare(dataset_root, REPO, GenSplatConfig(), episodes=[0], progress=False)
    with caplog.at_level(logging.WARNING):
        ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    assert ds.gensplat_cached == (1, 2)
    (warning,) = gensplat_warnings(caplog)
    assert "lacks 1 of 2 episodes" in warning and f"gensplat cache --root {dataset_root} --repo-id {REPO}" in warning


def test_demo_and_policies_use_one_repo_id():
    from gensplat_sim.demo import REPO_ID

    assert REPO_ID == SIM_REPO
    for config in POLICIES.glob("*.json"):
        assert json.loads(config.read_text())["dataset"]["repo_id"] == REPO_ID, config.name


def test_cli_user_mistakes_end_with_the_message(dataset_root, tmp_path, capsys):
    from gensplat_cli import main

    assert main(["cache", "--root", str(tmp_path / "nothing"), "--repo-id", REPO]) == 2
    err = capsys.readouterr().err
    assert err == f"gensplat: error: {tmp_path / 'nothing'}: not a local LeRobot dataset " \
                  f"({tmp_path / 'nothing' / 'meta' / 'info.json'} does not exist)\n"
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--render-scale", "2"]) == 2
    assert capsys.readouterr().err == "gensplat: error: GenSplatConfig.render_scale must be in (0, 1], got 2.0\n"
    info_path = dataset_root / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    for name in ("left", "right", "front"):  # no calibrated external camera left
        info["features"][f"observation.images.{name}"]["info"] = {}
    info_path.write_text(json.dumps(info))
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gensplat: error: ") and "needs a calibrated external camera" in err
    assert f"gensplat calibrate estimate --root {dataset_root}" in err and err.count("\n") == 1


def test_cache_command_writes_settings_and_cache(dataset_root, capsys):
    from gensplat_cli import main

    main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--level", "large", "--probability", "0.7"])
    out = capsys.readouterr().out
    assert "cached 2 episode(s)" in out
    assert f"repo id {REPO}, dataset root {dataset_root}; settings and cache in {dataset_root / 'gensplat'}" in out
    config, reconstructor = load_settings(dataset_root)
    assert config.level == "large" and config.probability == 0.7 and config.cameras == ("left", "right")
    assert reconstructor["name"] == "rgbd" and config.fill_holes
    assert config.render_in == "auto"
    record = json.loads((dataset_root / "gensplat" / "dataset.json").read_text())
    assert "weights_licence" not in record and "licence" not in out  # no model: no weights
    main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--no-fill-holes", "--render-in", "batch",
          "--render-scale", "0.5"])  # fmt: skip
    config = load_settings(dataset_root)[0]
    assert not config.fill_holes and config.render_in == "batch" and config.render_scale == 0.5
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--fill-depth", "8", "--sampler", "arc",
                 "--arc-deg", "30", "--focal-scale", "0.9", "1.2"]) == 0  # fmt: skip
    assert load_settings(dataset_root)[1] == {"name": "rgbd", "config": {"fill_depth_px": 8}}
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    assert ds.gensplat.cache.reconstructor.cfg.fill_depth_px == 8 and ds.gensplat.cache.status(0) == "ok"
    sampler = ds.gensplat.sampler  # the sampler the training workers draw from, as the settings say
    assert type(sampler).__name__ == "ArcSampler" and (sampler.limit_deg, sampler.focal_scale) == (30.0, (0.9, 1.2))
    capsys.readouterr()
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--fill-depth", "8", "--reconstructor",
                 "geometry"]) == 2  # fmt: skip
    assert capsys.readouterr().err.startswith("gensplat: error: --fill-depth fills the holes of measured depth")
    before = load_settings(dataset_root)
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--fill-depth", "-1"]) == 2
    assert capsys.readouterr().err == ("gensplat: error: RGBDConfig.fill_depth_px must be a whole number >= 0 "
                                       "(pixels), got -1\n")  # fmt: skip
    assert load_settings(dataset_root) == before  # refused before anything is written


def test_missing_settings_or_depth_raise_clear_errors(dataset_root):
    with pytest.raises(FileNotFoundError, match="gensplat cache"):
        enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    shutil.rmtree(dataset_root / "depth")
    save_settings(dataset_root, GenSplatConfig(cameras=("left", "right"), probability=1.0), {"name": "rgbd"})
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    with pytest.raises(ValueError, match="depths"):
        ds[0]
    info = json.loads((dataset_root / "meta" / "info.json").read_text())
    info["features"]["observation.images.front"]["info"] = {}  # an image feature without calibration
    (dataset_root / "meta" / "info.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match=re.escape("no calibration for camera(s) ['front']")):
        LeRobotSource(dataset_root, REPO, ("left", "front"))


@pytest.mark.parametrize("cameras", [("nope",), ("left", "nope")])
def test_an_unknown_camera_is_named_with_the_datasets_cameras(recorded, cameras):
    message = re.escape(f"{recorded}: no camera(s) ['nope']; its cameras: ['left', 'right', 'front']")
    with pytest.raises(ValueError, match=message):
        LeRobotSource(recorded, REPO, cameras)
    with pytest.raises(ValueError, match=message):
        LeRobotViews(recorded, REPO, cameras=cameras)
    assert LeRobotSource(recorded, REPO, "left").camera_names == ("left",)  # one name, not its letters


def test_an_info_json_without_features_is_refused(dataset_root):
    info = dataset_root / "meta" / "info.json"
    for text in ("{}", "not json", "[1, 2]"):
        info.write_text(text)
        with pytest.raises(ValueError, match=re.escape(f"{info}: not a LeRobot dataset's info")):
            LeRobotSource(dataset_root, REPO)


def test_frames_and_samples_out_of_range_are_refused(recorded):
    """A frame past an episode's end (or negative) is not read from the next (or previous)
    episode, nor a sample past the dataset's end left to a bare IndexError."""
    source = LeRobotSource(recorded, REPO)
    for frame in (20, -1):
        with pytest.raises(IndexError, match=re.escape(f"frame {frame} is not in episode 0 (frames 0..19)")):
            source.views(0, frame)
    views = LeRobotViews(recorded, REPO, size=PATCH_SIZE)
    assert len(views) == 40 and views[-1].images.shape[-1] == PATCH_SIZE
    with pytest.raises(IndexError, match=re.escape(f"LeRobotViews: sample 40 is out of range; {recorded} has 40")):
        views[40]


def copy_over(root: Path, camera: str, episode: int, to_camera: str, to_episode: int) -> None:
    shutil.copyfile(depth_path(root, camera, episode), depth_path(root, to_camera, to_episode))


def no_metadata(root: Path, frames: int, height: int = 48) -> None:
    """A depth file of left's episode 0 whose header records only its format."""
    depth = torch.ones(frames, height, 48, dtype=torch.float16)
    save_file({"depth": depth}, depth_path(root, "left", 0), metadata={"format": DEPTH_FORMAT})


@pytest.mark.parametrize("corrupt, file, message", [
    pytest.param(lambda root: copy_over(root, "left", 0, "right", 0), "right",
                 "says camera 'left', expected camera 'right'", id="another camera's"),
    pytest.param(lambda root: copy_over(root, "left", 1, "left", 0), "left",
                 "says episode '1', expected episode '0'", id="another episode's"),
    pytest.param(lambda root: save_depth(root, "left", 0, torch.ones(9, 48, 48)), "left",
                 "says num_frames '9', expected num_frames '20'", id="fewer frames"),
    pytest.param(lambda root: no_metadata(root, 21), "left", "21 frames of depth, the dataset's episode 0 has 20",
                 id="more frames, no metadata"),
    pytest.param(lambda root: no_metadata(root, 20, 40), "left", "depth maps of 48x40, expected 48x48",
                 id="another size"),
])  # fmt: skip
def test_a_depth_sidecar_that_does_not_match_the_dataset_is_refused(dataset_root, corrupt, file, message):
    """LeRobotViews (and every read of views) checks a depth sidecar's metadata and shape against the
    dataset as a cache build does, naming the file; again when the file changes."""
    views = LeRobotViews(dataset_root, REPO, size=PATCH_SIZE)
    assert views[1].depths is not None
    corrupt(dataset_root)
    with pytest.raises(ValueError, match=re.escape(f"{depth_path(dataset_root, file, 0)}: ") + ".*" + re.escape(message)):
        views[1]


def test_rgb_only_dataset_uses_the_geometry_path(dataset_root):
    shutil.rmtree(dataset_root / "depth")
    stats = prepare(dataset_root, REPO, GenSplatConfig(probability=1.0, level="small"), episodes=[0],
                    progress=False)  # fmt: skip
    assert stats[0].num_frames == 20
    _, reconstructor = load_settings(dataset_root)
    assert reconstructor["name"] == "geometry"
    assert stats[0].bytes_per_timestep < 64_000  # depth only
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    item, ref = ds[3], LeRobotDataset(REPO, root=dataset_root)[3]
    assert item[LEFT].shape == ref[LEFT].shape and torch.isfinite(item[LEFT]).all()
    assert not torch.equal(item[LEFT], ref[LEFT])


def test_the_dataset_record_keeps_the_licence_of_the_model_weights(dataset_root, tmp_path, capsys):
    """gensplat cache on the geometry path (a random checkpoint) records its weights' licence in
    <root>/gensplat/dataset.json and prints it from there; the field is not part of the content
    or its fingerprint, so a record without it (written before) still serves the cache."""
    from gensplat_cli import main
    from gensplat_lerobot.dataset import content_path, what_differs
    from tiny_model import tiny_model

    shutil.rmtree(dataset_root / "depth")
    ckpt = tiny_model().save_pretrained(tmp_path / "ckpt")
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--model", str(ckpt), "--episodes", "0",
                 "--probability", "1"]) == 0  # fmt: skip
    licence = "as its trainer set it (a gensplat train-model checkpoint)"
    assert f"model weights {ckpt}: licence {licence}\n" in capsys.readouterr().out
    record = json.loads(content_path(dataset_root).read_text())
    source = LeRobotSource(dataset_root, REPO)
    assert record == {"fingerprint": source.fingerprint, "content": json.loads(json.dumps(source.content)),
                      "weights_licence": licence}  # fmt: skip
    del record["weights_licence"]  # a record of an earlier version
    content_path(dataset_root).write_text(json.dumps(record))
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    assert ds.gensplat_cached == (1, 2) and ds.gensplat.cache.status(0) == "ok"
    assert what_differs(source) == f"cache files built for other content; the content now is {source.fingerprint}"


def test_max_pixels_caches_the_geometry_path_at_the_models_smaller_size(dataset_root, capsys):
    """gensplat cache --max-pixels: the model sees 28x28 of the 48x48 frames and the depth cache
    holds that size; the views are still rendered at the frames' size (the images' detail kept),
    and the policy is told when it reads less than half that."""
    from gensplat_cli import main

    shutil.rmtree(dataset_root / "depth")
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--max-pixels", "1000",
                 "--episodes", "0", "--probability", "1"]) == 0  # fmt: skip
    _, reconstructor = load_settings(dataset_root)
    assert reconstructor["name"] == "geometry" and reconstructor["options"] == {"max_pixels": 1000}
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))
    assert ds.gensplat.cache.image_size(0) == (28, 28)
    item, ref = ds[3], LeRobotDataset(REPO, root=dataset_root)[3]
    assert item[LEFT].shape == ref[LEFT].shape and torch.isfinite(item[LEFT]).all()
    from types import SimpleNamespace

    from gensplat_lerobot.plugin import render_warning, start_message
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig

    cfg = SimpleNamespace(policy=DiffusionConfig(), resume=False)  # reads the whole 48x48 frame
    lines = start_message(ds, cfg).splitlines()
    assert re.search(r"\(1 of 2 episodes cached\), reconstructor geometry-", lines[1])
    assert lines[3] == "  views rendered at 48x48 of 48x48 frames (render scale 1.0, cached at 28x28); the policy reads 48x48"
    assert lines[4].startswith("  a run resumed") and render_warning(ds, cfg) is None
    small = SimpleNamespace(policy=DiffusionConfig(resize_shape=(24, 24)), resume=False)
    assert start_message(ds, small).splitlines()[4] == (
        "  `gensplat cache` with --render-scale 0.5 renders what the policy reads, 24x24: 4.0x fewer pixels a view "
        "(render time falls about in proportion)")
    capsys.readouterr()
    assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--max-pixels", "1000",
                 "--reconstructor", "rgbd"]) == 2  # fmt: skip
    assert "--max-pixels need --reconstructor geometry, gensplat or monocular" in capsys.readouterr().err


def test_batch_timesteps_is_refused_where_no_geometry_model_runs(dataset_root, capsys):
    """With depth the default reconstructor is rgbd: a model batch size is refused, not ignored,
    as one error line."""
    from gensplat_cli import main

    for given in ([], ["--reconstructor", "rgbd"], ["--reconstructor", "gensplat"]):
        assert main(["cache", "--root", str(dataset_root), "--repo-id", REPO, "--batch-timesteps", "4", *given]) == 2
        err = capsys.readouterr().err
        assert err.startswith("gensplat: error: --batch-timesteps batches the geometry reconstructor's model; this")
        assert err.count("\n") == 1
    assert not (dataset_root / "gensplat").exists()  # refused before anything was written


def test_recorded_depth_is_imported_as_the_datasets_sidecars(dataset_root, tmp_path, capsys):
    """gensplat import-depth: millimetre PNGs of an RGB-only dataset become its depth
    sidecars, which the rgbd cache then links; user mistakes end with a message."""
    from gensplat_cli import main
    from PIL import Image

    want = {(n, e): load_depth(dataset_root, n, e)[:, 0] for n in ("left", "right") for e in (0, 1)}
    shutil.rmtree(dataset_root / "depth")
    for (name, episode), depth in want.items():
        folder = tmp_path / "raw" / f"episode_{episode}" / name
        folder.mkdir(parents=True)
        for t, frame in enumerate(depth):
            Image.fromarray((frame * 1000).round().numpy().astype("uint16")).save(folder / f"{t}.png")
    for name in ("left", "right"):
        args = ["import-depth", "--root", str(dataset_root), "--repo-id", REPO, "--camera", name,
                "--from", str(tmp_path / "raw" / "episode_{episode}" / name)]  # fmt: skip
        assert main(args) == 0
    assert "wrote the depth of 'right' for 2 episode(s), 40 frames" in capsys.readouterr().out
    for (name, episode), depth in want.items():
        got = load_depth(dataset_root, name, episode)[:, 0]
        assert (got - depth).abs().max() <= 0.5e-3 + 1e-3 * depth.max()  # millimetres, then float16
    assert main(args) == 0 and "2 episode(s) already had depth" in capsys.readouterr().out
    stats = prepare(dataset_root, REPO, GenSplatConfig(probability=1.0, level="small"), episodes=[0], progress=False)
    assert stats[0].bytes_per_timestep < 200  # links the imported files
    assert load_settings(dataset_root)[1]["name"] == "rgbd"
    for extra, message in ((["--camera", "top"], "no camera 'top'; its cameras"),
                           (["--episodes", "5"], r"episode\(s\) \[5\] are not in the dataset")):  # fmt: skip
        args = ["import-depth", "--root", str(dataset_root), "--repo-id", REPO, "--camera", "left",
                "--from", str(tmp_path / "raw" / "episode_{episode}" / "left"), *extra]  # fmt: skip
        assert main(args) == 2
        assert re.search(message, capsys.readouterr().err)


def test_pi0_config_parses_and_its_dataset_path_runs(dataset_root):
    import draccus
    import lerobot.policies  # noqa: F401  registers the policy config classes
    from lerobot.configs.train import TrainPipelineConfig
    from lerobot.datasets.factory import make_train_eval_datasets

    save_settings(dataset_root, GenSplatConfig(probability=1.0, report=True), {"name": "rgbd"})
    cfg = draccus.parse(TrainPipelineConfig, config_path=str(POLICIES / "pi0.json"),
                        args=[f"--dataset.repo_id={REPO}", f"--dataset.root={dataset_root}"])  # fmt: skip
    assert type(cfg.policy).__name__ == "PI0Config"
    cfg.validate()
    train, _ = make_train_eval_datasets(cfg)
    item = enable_gensplat(train)[3]
    assert item["gensplat.applied"].all() and item[LEFT].shape == (3, 48, 48)


@pytest.mark.parametrize("data", ["png_square", "mp4_non_square"])
def test_lerobot_train_diffusion_policy_with_the_one_line(data, request, tmp_path):
    """Two lerobot-train steps with the one GenSplat line: on the procedural 48x48 PNG dataset
    (views rendered at half size), and on the simulated 48x64 (HxW) MP4 recording (``gensplat
    record``, ``gensplat cache``)."""
    scale = 0.5 if data == "png_square" else 1.0
    if data == "png_square":
        dataset_root, repo = request.getfixturevalue("dataset_root"), REPO
        save_settings(dataset_root, GenSplatConfig(probability=1.0, render_scale=scale), {"name": "rgbd"})
    else:
        dataset_root, repo = tmp_path / "sim", SIM_REPO
        shutil.copytree(request.getfixturevalue("sim_video"), dataset_root)
        shutil.rmtree(dataset_root / "gensplat" / "cache")  # settings kept; the workers rebuild it
    out = tmp_path / "out"
    run = train_diffusion(f"--dataset.repo_id={repo}", f"--dataset.root={dataset_root}", f"--output_dir={out}",
                          "--steps=2", "--batch_size=2", "--num_workers=2", "--save_freq=2", "--log_freq=1")  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    log = run.stderr + run.stdout
    # at the start, one block: what GenSplat does, and that a resumed run needs the line again
    start = log[log.index("GenSplat enabled on the training dataset:") :].splitlines()[1:5]
    assert re.fullmatch(r"  cache: \S+gensplat/cache/rgbd-\w+ \(0 of \d episodes cached\), reconstructor rgbd-\w+", start[0])
    assert start[1] == "  probability 1.0, level train, mode episode, cameras replaced: left, right " \
                       "(reconstructed from left, right)"
    size = re.fullmatch(r"  views rendered at (\d+)x(\d+) of (\d+)x(\d+) frames \(render scale ([\d.]+)\); "
                        r"the policy reads (\d+)x(\d+)", start[2]).groups()  # fmt: skip
    w, h, width, height = (int(x) for x in size[:4])
    assert (w, h) == (round(width * scale), round(height * scale)) and float(size[4]) == scale
    assert ("smaller than the" in log) == (scale < 1)  # Diffusion Policy reads the frame at full size
    assert "--resume=true" in start[3] and "--gensplat.discover_packages_path=gensplat_lerobot.plugin" in start[3]
    # at every log step (--log_freq=1): counts gathered from the two spawn workers (which may
    # have made every sample the run needs by step 1: they prefetch)
    assert re.findall(r"GenSplat step (\d+): ", log) == ["1", "2"]
    steps = re.findall(r"GenSplat step \d+: (\d+) of (\d+) samples augmented \(100%\), ([\d.]+) ms per sample", log)
    assert steps and all(int(augmented) == int(samples) > 0 and float(ms) > 0 for augmented, samples, ms in steps)
    assert sum(int(samples) for _, samples, _ in steps) >= 4  # two steps of two samples
    # spawn workers built the cache while rendering: the augmentation really ran
    assert list((dataset_root / "gensplat" / "cache").rglob("episode_*.safetensors"))
    # the checkpoint knows nothing about GenSplat: it loads without this package
    saved = next(out.rglob("train_config.json")).read_text()
    assert "gensplat_lerobot" not in saved and "discover_packages_path" not in saved
    for saved_file in out.rglob("*.json"):  # nor do the processors' configs and stats
        assert "gensplat_lerobot" not in saved_file.read_text() and '"gensplat.' not in saved_file.read_text()
    policy_cfg = json.loads(next(out.rglob("pretrained_model/config.json")).read_text())
    assert policy_cfg["type"] == "diffusion"


def test_policy_input_size_is_read_and_a_smaller_render_is_warned_of(dataset_root):
    from types import SimpleNamespace

    from gensplat_lerobot.plugin import policy_input_size, render_warning, start_message
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.pi0.configuration_pi0 import PI0Config
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig

    assert policy_input_size(DiffusionConfig(), 640, 480) == (640, 480)  # it crops at full size
    assert policy_input_size(DiffusionConfig(resize_shape=(240, 320)), 640, 480) == (320, 240)
    assert policy_input_size(PI0Config(), 640, 480) == (224, 168)  # fit into 224x224, aspect kept
    assert policy_input_size(SmolVLAConfig(resize_imgs_with_padding=(512, 256)), 640, 480) == (341, 256)
    assert policy_input_size(ACTConfig(), 640, 480) == (640, 480)
    assert policy_input_size(SimpleNamespace(type="vqbet"), 640, 480) is None
    assert policy_input_size(SimpleNamespace(type="pi0"), 640, 480) is None  # a version without the field
    save_settings(dataset_root, GenSplatConfig(probability=1.0, render_scale=0.5), {"name": "rgbd"})
    ds = enable_gensplat(LeRobotDataset(REPO, root=dataset_root))  # 48x48 frames
    full, half = (SimpleNamespace(policy=p, resume=False) for p in (DiffusionConfig(),
                                                                    DiffusionConfig(resize_shape=(24, 24))))
    assert render_warning(ds, full) == (
        "GenSplat renders its views at 24x24 (render scale 0.5), smaller than the 48x48 the policy reads: augmented "
        "samples are blurrier than the others; run `gensplat cache` with --render-scale 1 or more")
    assert render_warning(ds, half) is None and render_warning(ds, SimpleNamespace(policy=None)) is None
    lines = start_message(ds, half).splitlines()
    assert lines[3] == "  views rendered at 24x24 of 48x48 frames (render scale 0.5); the policy reads 24x24"


def test_a_killed_writers_temporary_file_is_not_dataset_content(dataset_root):
    """A depth import or calibration killed mid-write leaves atomic_write's temporary file
    beside the sidecars: the folder's digest (and so the cache's dataset fingerprint) ignores
    it, where a real new file counts."""
    from gensplat_lerobot.source import files_digest

    before = files_digest(dataset_root, "depth/left")
    (dataset_root / "depth" / "left" / ".episode_000000.safetensors.0123456789ab.tmp").write_bytes(b"partial")
    assert files_digest(dataset_root, "depth/left") == before
    (dataset_root / "depth" / "left" / "episode_000002.safetensors").write_bytes(b"new")
    assert files_digest(dataset_root, "depth/left") != before


def test_folder_digests_are_remembered_by_file_stats(dataset_root, monkeypatch):
    from pathlib import Path as P

    from gensplat_lerobot.source import files_digest

    from gensplat_transforms.data.format import digests_path

    memo, folder = digests_path(dataset_root), "depth/left"
    plain = files_digest(dataset_root, folder)
    assert files_digest(dataset_root, folder, memo) == plain and not memo.exists()  # no gensplat/ folder made
    memo.parent.mkdir()
    assert files_digest(dataset_root, folder, memo) == plain and folder in json.loads(memo.read_text())
    opened, open_ = [], P.open
    monkeypatch.setattr(P, "open", lambda self, *a, **k: opened.append(self.parent) or open_(self, *a, **k))
    assert files_digest(dataset_root, folder, memo) == plain
    assert dataset_root / folder not in opened  # from the memo: no depth file read
    depth = min((dataset_root / folder).iterdir())
    data = bytearray(depth.read_bytes())
    data[-1] ^= 0xFF  # same size, new modification time
    depth.write_bytes(bytes(data))
    changed = files_digest(dataset_root, folder, memo)
    assert changed != plain and changed == files_digest(dataset_root, folder) and dataset_root / folder in opened
    memo.write_text("{not json")
    assert files_digest(dataset_root, folder, memo) == changed and folder in json.loads(memo.read_text())


def test_folder_digest_keeps_its_formula(tmp_path):
    """Caches are keyed by these digests: a change of formula would make every cache stale."""
    import hashlib

    from gensplat_lerobot.source import files_digest

    (tmp_path / "v" / "a" / "b").mkdir(parents=True)
    (tmp_path / "v" / "a-c").mkdir()
    for name, data in {"a/b/f": b"x", "a-c/g": b"yy", "a.txt": b"z", "big": bytes(range(256)) * 200}.items():
        (tmp_path / "v" / name).write_bytes(data)
    (tmp_path / "v" / "link").symlink_to(tmp_path / "v" / "a.txt")
    (tmp_path / "v" / "broken").symlink_to(tmp_path / "nothing")
    (tmp_path / "v" / "dirlink").symlink_to(tmp_path / "v" / "a")
    h = hashlib.sha256()
    for rel in ("v/a/b/f", "v/a-c/g", "v/a.txt", "v/big", "v/link"):  # pathlib's order; no broken or folder link
        data = (tmp_path / rel).read_bytes()
        h.update(f"{rel}\0{len(data)}\0".encode() + data[:16384] + data[max(16384, len(data) - 16384):])
    assert files_digest(tmp_path, "v") == h.hexdigest()


def test_progress_line_says_when_the_workers_are_ahead():
    from gensplat_lerobot.plugin import progress_message

    assert progress_message(2, 8, 4, 0.2) == "GenSplat step 2: 4 of 8 samples augmented (50%), 25.0 ms per sample in the workers"
    assert progress_message(4, 0, 0, 0.0) == "GenSplat step 4: no samples made since the last report (the workers are ahead)"


def test_plugin_without_settings_stops_training(dataset_root, tmp_path):
    run = train_diffusion(f"--dataset.repo_id={REPO}", f"--dataset.root={dataset_root}",
                          f"--output_dir={tmp_path / 'o'}", "--steps=1", "--batch_size=2", "--num_workers=0")  # fmt: skip
    assert run.returncode != 0
    last = run.stderr.strip().splitlines()[-1]  # lerobot-train's traceback ends with our message alone
    assert last == (f"FileNotFoundError: GenSplat is enabled but {dataset_root / 'gensplat' / 'config.json'} does not "
                    f"exist: run `gensplat cache --root {dataset_root} --repo-id {REPO}` once to write the settings "
                    "and build the Gaussian cache")  # fmt: skip


def test_episode_lengths_and_starts_come_from_one_metadata_read(dataset_root):
    """LeRobotSource reads every episode's length and first index once, as LeRobot's
    metadata has them, and refuses an episode outside the dataset (no negative indexing)."""
    source = LeRobotSource(dataset_root, REPO)
    meta = source.dataset.meta
    assert [source.num_frames(e) for e in range(meta.total_episodes)] == [int(n) for n in meta.episodes["length"]]
    start = int(meta.episodes["dataset_from_index"][1])
    item = LeRobotDataset(REPO, root=dataset_root)[start + 3]
    want = item[f"observation.images.{source.camera_names[0]}"]
    got = source.views(1, 3).images[0]
    assert torch.allclose(got, want.float() / 255 if want.dtype == torch.uint8 else want)
    with pytest.raises(IndexError, match=r"episode -1 is not in the dataset \(episodes 0..1\)"):
        source.num_frames(-1)
    with pytest.raises(IndexError, match="episode 2 is not in the dataset"):
        source.views(2, 0)


def assert_episode_views_are_the_views(source: LeRobotSource, episode: int) -> None:
    """What a cache build reads, ``episode_views``, is ``views`` of every frame, tensor for tensor."""
    every = list(source.episode_views(episode))
    assert len(every) == source.num_frames(episode)
    for frame in (0, 1, len(every) // 2, len(every) - 1):
        want, got = source.views(episode, frame), every[frame]
        assert torch.equal(got.images, want.images) and torch.equal(got.cameras.c2w, want.cameras.c2w)
        assert (got.depths is None and want.depths is None) or torch.equal(got.depths, want.depths)


def test_a_build_decodes_only_the_reconstructed_cameras_videos_and_gets_the_same_views(sim_video, recorded):
    """MP4 frames of the two external cameras (the wrist's is not decoded) in chunks of
    DECODE_CHUNK, over an episode whose length is not a multiple of it; a dataset stored as
    images reads item by item."""
    from gensplat_lerobot.source import DECODE_CHUNK

    source = LeRobotSource(sim_video, SIM_REPO)
    assert source.num_frames(0) % DECODE_CHUNK and source.num_frames(0) > 2 * DECODE_CHUNK
    assert_episode_views_are_the_views(source, 0)
    decode, asked = source.dataset.reader._query_videos, []
    source.dataset.reader._query_videos = lambda query, ep: asked.append(query) or decode(query, ep)
    next(source.episode_views(0))
    assert [sorted(q) for q in asked] == [[LEFT, "observation.images.right"]]
    assert [len(t) for t in asked[0].values()] == [DECODE_CHUNK] * 2
    assert_episode_views_are_the_views(LeRobotSource(recorded, REPO), 1)


@pytest.mark.parametrize(("depth_as", "error_m"), [("feature", 0.5e-3), ("video", 2e-3)])
def test_lerobots_own_depth_features_are_read_and_copied_into_the_cache(tmp_path, depth_as, error_m, capsys):
    """A dataset whose cameras' depth is LeRobot's depth-map feature (observation.images.<cam>_depth,
    uint16 mm, as LeRobot records a RealSense: PNG images, or its 12-bit log-quantised HEVC
    video beside MP4 colour video) and no sidecars: the RGB-D path is chosen, the views carry
    that depth in metres (within the millimetre rounding, plus LeRobot's 12-bit steps of about
    1 mm at 3 m for video), the cache stores a compressed copy (nothing to link), and the
    transform renders the depth features at the new pose too, in the dataset's unit (kept as
    recorded with --keep-depth-maps)."""
    root = tmp_path / "ds"
    source = SceneEpisodes(num_episodes=2, num_frames=4, size=32)
    record_scene_dataset(root, source, REPO, progress=False, depth_as=depth_as)
    assert not (root / "depth").exists()
    assert (root / "videos" / "observation.images.left_depth").is_dir() == (depth_as == "video")
    lerobot_source = LeRobotSource(root, REPO)
    assert lerobot_source.camera_names == ("left", "right") and lerobot_source.has_depth()
    want = source.render(0, 2)[1][:2]
    got = lerobot_source.views(0, 2).depths
    assert (got - want).abs().max() <= error_m + 1e-6
    assert lerobot_source.depth_files(0) is None
    assert_episode_views_are_the_views(lerobot_source, 1)  # videos decoded in chunks, from the episode's start
    stats = prepare(root, REPO, GenSplatConfig(probability=1.0, level="small"), progress=False)
    assert load_settings(root)[1]["name"] == "rgbd" and stats[0].bytes_per_timestep > 200  # a stored copy
    from types import SimpleNamespace

    from gensplat_cli import main
    from gensplat_lerobot.plugin import start_message

    for unit in ("mm", "m"):  # LeRobot's default, and metres
        opened = {"root": root, "video_backend": video_backend(), "depth_output_unit": unit}
        ds = enable_gensplat(LeRobotDataset(REPO, **opened))
        item, ref = ds[2], LeRobotDataset(REPO, **opened)[2]
        assert not torch.equal(item[LEFT], ref[LEFT]) and torch.isfinite(item[LEFT]).all()
        depth, recorded = item[LEFT + "_depth"], ref[LEFT + "_depth"]
        assert depth.shape == recorded.shape and depth.dtype == recorded.dtype and not torch.equal(depth, recorded)
        both = (depth > 0) & (recorded > 0)  # a small move: the same unit, depths within 10 %
        assert both.float().mean() > 0.7 and ((depth - recorded).abs() / recorded)[both].median() < 0.1
        lines = start_message(ds, SimpleNamespace(policy=None, resume=False)).splitlines()
        assert lines[4] == (f"  depth maps {LEFT}_depth, observation.images.right_depth rendered at the new poses too, "
                            f"in {unit}")  # fmt: skip
    from gensplat_lerobot.plugin import run_settings

    right_depth = "observation.images.right_depth"
    for reads in ({LEFT: None}, {LEFT: None, right_depth: None}):  # a policy whose input features are given
        run = SimpleNamespace(policy=SimpleNamespace(input_features=reads), resume=False)
        base = LeRobotDataset(REPO, **opened)
        ds = enable_gensplat(base, *run_settings(base, run))  # as the plugin makes it
        item = ds[2]
        assert not torch.equal(item[LEFT], ref[LEFT])
        assert torch.equal(item[LEFT + "_depth"], ref[LEFT + "_depth"]) == (right_depth not in reads)
        assert start_message(ds, run).splitlines()[4] == (
            f"  depth maps {LEFT}_depth, {right_depth} kept as recorded: the policy does not read them "
            "(its input_features)" if right_depth not in reads
            else f"  depth maps {LEFT}_depth, {right_depth} rendered at the new poses too, in m")  # fmt: skip
    assert main(["cache", "--root", str(root), "--repo-id", REPO, "--keep-depth-maps", "--probability", "1"]) == 0
    tip = "tip: the depth of left, right is a sensor's (LeRobot depth maps): --fill-depth 8 gives its small holes"
    assert tip in capsys.readouterr().out
    assert main(["cache", "--root", str(root), "--repo-id", REPO, "--keep-depth-maps", "--fill-depth", "8",
                 "--probability", "1"]) == 0
    assert "tip:" not in capsys.readouterr().out
    ds = enable_gensplat(LeRobotDataset(REPO, **opened))
    item = ds[2]
    assert torch.equal(item[LEFT + "_depth"], ref[LEFT + "_depth"]) and not torch.equal(item[LEFT], ref[LEFT])
    assert "kept as recorded (--keep-depth-maps)" in start_message(ds, SimpleNamespace(policy=None, resume=False))
    (words, coded), _ = ds.gensplat.cache.read_depth_words(0, 2)
    from gensplat_transforms.cache.depth_codec import depth_from_words

    assert (depth_from_words(words, coded) - want[:, 0]).abs().max() <= 1e-3 * want.max() + error_m
