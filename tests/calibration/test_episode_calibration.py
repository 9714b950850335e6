"""Per-episode camera poses: given to ``gensplat calibrate`` in a file or read from DROID-style
``camera_extrinsics.<camera>`` features, used by the LeRobot source per episode, in the cache
fingerprint, the cache and the transform's renders."""

import json
import math
import os
import re
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from gensplat_cli import main
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from gensplat_transforms.calibration.files import calibrate, load_calibration, xyz_rpy_pose
from gensplat_transforms.data.format import calibration_path

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed")
os.environ["HF_HUB_OFFLINE"] = "1"

from gensplat_lerobot import LeRobotSource, enable_gensplat, prepare, video_backend
from helpers import strip_calibration
from lerobot.datasets.lerobot_dataset import LeRobotDataset

from gensplat_transforms.transform import GenSplatConfig

REPO = "local/moving_cameras"
NAMES = ("left", "right")
FRAMES = 3


@pytest.fixture(scope="module")
def recorded(scene_dataset, tmp_path_factory):
    """Two episodes of 3 frames at 32x32 whose features carry no calibration (depth sidecars
    kept), and the recorded (static) cameras as {name: (K, c2w)}."""
    root = shutil.copytree(scene_dataset(REPO, episodes=2, frames=FRAMES, size=32),
                           tmp_path_factory.mktemp("episodes") / "ds")  # fmt: skip
    calib = LeRobotSource(root, REPO).calibration
    strip_calibration(root, (*NAMES, "front"))
    return root, {n: (calib[n].K, calib[n].c2w) for n in NAMES}


@pytest.fixture
def dataset(recorded, dataset_copy):
    return dataset_copy(recorded[0]), recorded[1]


def moved(c2w: torch.Tensor, dx: float = 0.08, angle: float = 0.15) -> torch.Tensor:
    """``c2w`` shifted along world x and turned about its own y axis."""
    out = c2w.clone()
    turn = axis_angle_to_rotation_matrix(torch.tensor([[0.0, angle, 0.0]], dtype=c2w.dtype))[0]
    out[:3, :3] = c2w[:3, :3] @ turn
    out[0, 3] += dx
    return out


def per_episode(truth: dict, first: dict) -> dict:
    """gensplat-convention file: left listed per episode (no default pose), right with its
    recorded pose as default and episode 0 listed; ``first`` holds episode 0's poses."""
    (K_l, c2w_l), (K_r, c2w_r) = truth["left"], truth["right"]
    return {"left": {"K": K_l.tolist(), "episodes": {"0": {"c2w": first["left"].tolist()}, "1": {"c2w": c2w_l.tolist()}}},
            "right": {"K": K_r.tolist(), "c2w": c2w_r.tolist(), "episodes": {"0": {"c2w": first["right"].tolist()}}}}  # fmt: skip


def to_w2c(c2w: torch.Tensor) -> dict:
    R = c2w[:3, :3].T
    return {"R": R.tolist(), "t": (-R @ c2w[:3, 3]).tolist()}


def write(folder: Path, data: dict, name: str = "calibration.json") -> Path:
    path = folder / name
    path.write_text(yaml.safe_dump(data) if name.endswith(".yaml") else json.dumps(data))
    return path


@pytest.mark.parametrize("form", ["gensplat", "opencv-w2c", "yaml-int-keys"])
def test_views_carry_each_episodes_poses(form, dataset, tmp_path):
    root, truth = dataset
    first = {n: moved(truth[n][1]) for n in NAMES}
    data = per_episode(truth, first)
    if form == "opencv-w2c":  # pixel centres at integers
        K = {n: (truth[n][0] - torch.tensor([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]], dtype=torch.float64)).tolist()
             for n in NAMES}  # fmt: skip
        data = {"left": {"K": K["left"], "episodes": {"0": to_w2c(first["left"]), "1": to_w2c(truth["left"][1])}},
                "right": {"K": K["right"], **to_w2c(truth["right"][1]), "episodes": {"0": to_w2c(first["right"])}}}  # fmt: skip
    if form == "yaml-int-keys":
        data = {n: {**e, "episodes": {int(k): v for k, v in e["episodes"].items()}} for n, e in data.items()}
    path = write(tmp_path, data, "calibration.yaml" if form == "yaml-int-keys" else "calibration.json")
    assert main(["calibrate", "from-file", "--root", str(root), str(path)]) == 0
    stored = json.loads(calibration_path(root).read_text())["cameras"]
    assert set(stored["left"]["camera.episodes"]) == {"0", "1"} and "camera.extrinsics" not in stored["left"]
    assert set(stored["right"]["camera.episodes"]) == {"0"} and "camera.extrinsics" in stored["right"]

    source = LeRobotSource(root, REPO)
    assert source.camera_names == NAMES
    expected = {0: torch.stack([first[n] for n in NAMES]), 1: torch.stack([truth[n][1] for n in NAMES])}
    for episode, c2w in expected.items():
        for views in (source.views(episode, 1), list(source.episode_views(episode))[1]):
            torch.testing.assert_close(views.cameras.c2w, c2w, rtol=0, atol=1e-9)
            assert views.depths is not None
        torch.testing.assert_close(source.depth_files(episode).cameras.c2w, c2w, rtol=0, atol=1e-9)
    torch.testing.assert_close(source.cameras.K, torch.stack([truth[n][0] for n in NAMES]), rtol=0, atol=1e-9)


def test_the_fingerprint_follows_each_episodes_pose(dataset, tmp_path):
    root, truth = dataset
    first = {n: moved(truth[n][1]) for n in NAMES}
    calibrate(root, write(tmp_path, {n: {"K": K.tolist(), "c2w": c2w.tolist()} for n, (K, c2w) in truth.items()}))
    static = LeRobotSource(root, REPO)
    assert all("camera.episodes" not in info for _, _, info in static.content["cameras"])  # the static form is kept
    calibrate(root, write(tmp_path, per_episode(truth, first)))
    before = LeRobotSource(root, REPO).fingerprint
    first["right"] = moved(truth["right"][1], dx=0.0801)  # one episode's pose of one camera, by 0.1 mm
    calibrate(root, write(tmp_path, per_episode(truth, first)))
    assert len({static.fingerprint, before, LeRobotSource(root, REPO).fingerprint}) == 3


def test_the_cache_and_the_transform_use_each_episodes_poses(dataset, tmp_path):
    """Episode 1 of a dataset whose cameras moved after episode 0 renders as the same episode
    of a copy calibrated statically at episode 1's poses; episode 0 does not."""
    root, truth = dataset
    static = tmp_path / "static"
    shutil.copytree(root, static)
    calibrate(root, write(tmp_path, per_episode(truth, {n: moved(truth[n][1]) for n in NAMES})))
    calibrate(static, write(tmp_path, {n: {"K": K.tolist(), "c2w": c2w.tolist()} for n, (K, c2w) in truth.items()}))
    config = GenSplatConfig(probability=1.0, level="large", views_per_source=1, report=True)
    items = {}
    for r in (root, static):
        prepare(r, REPO, config, progress=False)
        ds = enable_gensplat(LeRobotDataset(REPO, root=r, video_backend=video_backend()))
        items[r] = []
        for index in (0, FRAMES):  # episode 0 and episode 1, frame 0
            torch.manual_seed(0)
            items[r].append(ds[index])
    for n in NAMES:
        key = f"observation.images.{n}"
        assert items[root][1]["gensplat.applied"].all()
        torch.testing.assert_close(items[root][1][key], items[static][1][key], rtol=0, atol=0)
        assert (items[root][0][key] - items[static][0][key]).abs().max() > 0.05


def droid_like(root: Path, poses: list[list[float]], drift: float = 0.0) -> Path:
    """A DROID-shaped dataset: wrist_left, exterior_1_left, exterior_2_left (24x32 images) and
    their camera_extrinsics.<camera> (6,) features, one episode per pose of exterior_1_left
    (exterior_2_left 0.5 m beside it), the last frame of each episode ``drift`` off."""
    names = ("wrist_left", "exterior_1_left", "exterior_2_left")
    features = {f"observation.images.{n}": {"dtype": "image", "shape": (24, 32, 3), "names": ["height", "width", "channels"]}
                for n in names}  # fmt: skip
    for n in names:
        features[f"camera_extrinsics.{n}"] = {"dtype": "float32", "shape": (6,),
                                              "names": {"axes": ["x", "y", "z", "roll", "pitch", "yaw"]}}  # fmt: skip
    ds = LeRobotDataset.create("local/droid_like", 15, features, root=root, use_videos=False)
    for pose in poses:
        for t in range(FRAMES):
            frame = {f"observation.images.{n}": torch.rand(24, 32, 3).numpy() for n in names}
            off = drift if t == FRAMES - 1 else 0.0
            frame["camera_extrinsics.exterior_1_left"] = torch.tensor([*pose[:3], pose[3] + off, *pose[4:]]).numpy()
            frame["camera_extrinsics.exterior_2_left"] = torch.tensor([pose[0] + 0.5, *pose[1:]]).numpy()
            frame["camera_extrinsics.wrist_left"] = torch.tensor([0.0, 0, 0.3, 0, 0, 0]).numpy()
            frame["task"] = "t"
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    return root


DROID_POSES = [[0.2, -0.5, 0.6, -2.0, 0.1, 1.4], [0.1, 0.4, 0.5, -1.9, -0.2, -1.2]]


def test_xyz_rpy_is_extrinsic_xyz_camera_to_world():
    """The documented convention: R = Rz(yaw) Ry(pitch) Rx(roll), translation the camera centre."""
    x, y, z, roll, pitch, yaw = 0.3, -0.2, 0.7, 0.4, -0.6, 1.1

    def about(axis: int, angle: float) -> torch.Tensor:
        v = torch.zeros(1, 3, dtype=torch.float64)
        v[0, axis] = angle
        return axis_angle_to_rotation_matrix(v)[0]

    c2w = xyz_rpy_pose([x, y, z, roll, pitch, yaw])
    torch.testing.assert_close(c2w[:3, :3], about(2, yaw) @ about(1, pitch) @ about(0, roll), rtol=0, atol=1e-12)
    torch.testing.assert_close(c2w[:3, 3], torch.tensor([x, y, z], dtype=torch.float64))
    torch.testing.assert_close(c2w[3], torch.tensor([0.0, 0, 0, 1], dtype=torch.float64))


@pytest.mark.parametrize("given", ["fov", "intrinsics"])
def test_droid_camera_extrinsics_features_become_per_episode_poses(given, tmp_path, capsys):
    root = droid_like(tmp_path / "droid", DROID_POSES)
    if given == "fov":
        option, K = ["--fov", "90"], torch.tensor([[16.0, 0, 16], [0, 16, 12], [0, 0, 1]], dtype=torch.float64)
    else:  # a calibration file in OpenCV's convention, K only
        file = write(tmp_path, {n: {"fx": 20.0, "fy": 21.0, "cx": 15.0, "cy": 11.0, "R": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                    "t": [0, 0, 0]} for n in ("exterior_1_left", "exterior_2_left")})  # fmt: skip
        option, K = ["--intrinsics", str(file)], torch.tensor([[20.0, 0, 15.5], [0, 21, 11.5], [0, 0, 1]], dtype=torch.float64)
    assert main(["calibrate", "from-features", "--root", str(root), *option]) == 0
    assert "exterior_1_left (2 episodes), exterior_2_left (2 episodes)" in capsys.readouterr().out
    info = json.loads((root / "meta" / "info.json").read_text())
    calib = load_calibration(info["features"], root, 2)
    assert sorted(calib) == ["exterior_1_left", "exterior_2_left"]  # the wrist camera is left out
    source = LeRobotSource(root, "local/droid_like")
    for e, pose in enumerate(DROID_POSES):
        beside = xyz_rpy_pose([pose[0] + 0.5, *pose[1:]])
        for n, c2w in (("exterior_1_left", xyz_rpy_pose(pose)), ("exterior_2_left", beside)):
            torch.testing.assert_close(calib[n].episodes[e], c2w, rtol=0, atol=1e-6)  # float32 features
            torch.testing.assert_close(calib[n].K, K)
        torch.testing.assert_close(source.views(e, 1).cameras.c2w[0], xyz_rpy_pose(pose), rtol=0, atol=1e-6)


@pytest.mark.parametrize("case, message", [
    ("missing_episode", r"camera 'left': episode\(s\) \[1\] of the dataset's 2 have no pose: .* a default pose \(c2w\)"),
    ("unknown_episode", r"calibration.json: camera 'left', episode 5: the dataset has no episode 5 \(its episodes: 0..1\)"),
    ("not_an_index", r"camera 'left', field episodes: 'last' is not an episode index"),
    ("non_rigid", r"camera 'left', episode 1, field c2w: .*not orthonormal with det \+1"),
    ("non_rigid_w2c", r"camera 'left', episode 1, field R, t: .*not orthonormal"),
    ("no_pose", r"camera 'left', episode 1: needs its pose \(c2w\)"),
    ("wrist", r"camera 'left': per-episode poses \(field episodes\) are for external cameras"),
])  # fmt: skip
def test_bad_per_episode_poses_name_file_camera_and_episode(case, message, dataset, tmp_path):
    root, truth = dataset
    data = per_episode(truth, {n: moved(truth[n][1]) for n in NAMES})
    left, scaled = data["left"], truth["left"][1].clone()
    scaled[:3, :3] *= 1.1
    if case == "missing_episode":
        del left["episodes"]["1"]
    elif case == "unknown_episode":
        left["episodes"]["5"] = left["episodes"]["1"]
    elif case == "not_an_index":
        left["episodes"]["last"] = left["episodes"]["1"]
    elif case == "non_rigid":
        left["episodes"]["1"] = {"c2w": scaled.tolist()}
    elif case == "non_rigid_w2c":
        left["episodes"] = {"0": to_w2c(truth["left"][1]), "1": {**to_w2c(truth["left"][1]), "R": scaled[:3, :3].tolist()}}
    elif case == "no_pose":
        left["episodes"]["1"] = {}
    else:
        left["mount"] = "wrist"
    with pytest.raises(ValueError, match=message):
        calibrate(root, write(tmp_path, data))
    assert not calibration_path(root).exists()


def test_a_stored_calibration_for_episodes_the_dataset_lacks_is_refused(dataset, tmp_path):
    root, truth = dataset
    calibrate(root, write(tmp_path, per_episode(truth, {n: moved(truth[n][1]) for n in NAMES})))
    data = json.loads(calibration_path(root).read_text())
    data["cameras"]["right"]["camera.episodes"]["7"] = data["cameras"]["right"]["camera.extrinsics"]
    calibration_path(root).write_text(json.dumps(data))
    with pytest.raises(ValueError, match=r"calibration.json: camera 'right', episode 7: the dataset has no episode 7 .*"
                                         r"write it again with `gensplat calibrate"):  # fmt: skip
        LeRobotSource(root, REPO)


@pytest.mark.parametrize("args, message", [
    (["from-features", "--fov", "60", "--principal-point", "100,90"],
     r"calibrate from-features does not read --principal-point \(only estimate\)$"),
    (["from-file", "calibration.json", "--fov", "60", "--timesteps", "4"],
     r"calibrate from-file does not read --fov \(only from-features and estimate\); --timesteps \(only estimate\)$"),
    (["estimate", "--convention", "gensplat", "--intrinsics", "k.json"],
     r"calibrate estimate does not read --convention \(only from-file\); --intrinsics \(only from-features\)$"),
])  # fmt: skip
def test_calibrate_refuses_options_its_way_does_not_read(args, message, tmp_path, capsys):
    """An option the chosen way of calibrating does not read is refused, naming the ways that
    read it, before anything is read or written."""
    assert main(["calibrate", *args, "--root", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("gensplat: error: ") and err.count("\n") == 1 and re.search(message, err.strip())


@pytest.mark.parametrize("case, message", [
    ("drift", r"camera_extrinsics.exterior_1_left changes within episode 0 by up to 0.01 .*leave it out with --cameras"),
    ("no_intrinsics", r"give the cameras' intrinsics with one of --intrinsics FILE, --fov or --focal"),
    ("no_feature", r"camera\(s\) \['front'\] have no camera_extrinsics.<camera> feature"),
])  # fmt: skip
def test_droid_features_errors(case, message, tmp_path, capsys):
    root = droid_like(tmp_path / "droid", DROID_POSES, drift=0.01 if case == "drift" else 0.0)
    args = {"drift": ["--fov", "60"], "no_intrinsics": [], "no_feature": ["--fov", "60", "--cameras", "front"]}[case]
    capsys.readouterr()
    assert main(["calibrate", "from-features", "--root", str(root), *args]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.startswith("gensplat: error: ") and err.count("\n") == 1
    assert not calibration_path(root).exists()


def _rewrite_rows(root: Path, key: str, change) -> None:
    """Replace the ``key`` column of the dataset's parquet files: ``change(episode, frame, row)``
    gives each row's new list of values."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    for file in sorted((root / "data").rglob("*.parquet")):
        table = pq.read_table(file)
        rows = [change(e, f, r) for e, f, r in zip(*(table[c].to_pylist() for c in ("episode_index", "frame_index", key)))]
        column = pa.array(rows, type=pa.list_(pa.float32()))
        pq.write_table(table.set_column(table.schema.get_field_index(key), key, column), file)


@pytest.mark.parametrize("case, message", [
    ("nan", r"camera_extrinsics.exterior_1_left is not a finite pose at episode 1, frame 2 \(\[nan, "),
    ("nan_and_moving", r"camera_extrinsics.exterior_1_left is not a finite pose at episode 0, frame 1"),
    ("five", r"camera_extrinsics.exterior_1_left holds 5 values at episode 0, frame 0; a pose is 6"),
    ("twice", r"--cameras names \['exterior_1_left'\] more than once"),
])  # fmt: skip
def test_feature_poses_that_are_not_poses_are_named(case, message, tmp_path, capsys):
    """One NaN frame no longer hides a camera that moves 1 m in its episode; rows of the wrong
    length and a camera named twice are clear errors, not IndexError or KeyError."""
    root = droid_like(tmp_path / "droid", DROID_POSES, drift=1.0 if case == "nan_and_moving" else 0.0)
    key = "camera_extrinsics.exterior_1_left"
    if case == "nan":
        _rewrite_rows(root, key, lambda e, f, r: [math.nan] * 6 if (e, f) == (1, 2) else r)
    elif case == "nan_and_moving":
        _rewrite_rows(root, key, lambda e, f, r: [math.nan, *r[1:]] if (e, f) == (0, 1) else r)
    elif case == "five":
        _rewrite_rows(root, key, lambda e, f, r: r[:5])
    cameras = ["--cameras", "exterior_1_left", "exterior_1_left"] if case == "twice" else []
    capsys.readouterr()
    assert main(["calibrate", "from-features", "--root", str(root), "--fov", "60", *cameras]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err) and err.startswith("gensplat: error: ") and err.count("\n") == 1, err
    assert not calibration_path(root).exists()
