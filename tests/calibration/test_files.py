"""``gensplat calibrate``: calibration of a dataset whose features carry none, in three
conventions, stored beside the dataset (never in it) and used by the LeRobot source."""

import json
import os
import shutil
from pathlib import Path

import pytest
import torch
import yaml
from gensplat_cli import main
from helpers import strip_calibration, write_image_features
from kornia.geometry.conversions import rotation_matrix_to_axis_angle

from gensplat_transforms.calibration.files import calibrate, load_calibration
from gensplat_transforms.core.cameras import opencv_to_opengl
from gensplat_transforms.data.format import calibration_path
from gensplat_transforms.data.scenes import default_cameras

WIDTH, HEIGHT = 64, 48
NAMES = ("left", "right", "front")


@pytest.fixture
def truth():
    """The three default cameras at 64x48 with an off-centre principal point each."""
    cams = default_cameras(WIDTH, HEIGHT)
    K = cams.K.clone()
    K[:, 0, 2] += torch.tensor([3.25, -2.0, 0.5], dtype=K.dtype)
    K[:, 1, 2] += torch.tensor([-1.5, 2.75, 0.0], dtype=K.dtype)
    return {n: (K[i], cams.c2w[i]) for i, n in enumerate(NAMES)}


def write_info(root: Path, names=(*NAMES, "wrist")) -> dict:
    """A dataset's ``meta/info.json`` whose image features (WIDTH x HEIGHT) carry no calibration."""
    return write_image_features(root, names, WIDTH, HEIGHT)


def w2c(K: torch.Tensor, c2w: torch.Tensor) -> dict:
    """OpenCV's world-to-camera R, t and K (pixel centres at integers)."""
    R = c2w[:3, :3].T
    K = K.clone()
    K[:2, 2] -= 0.5
    return {"K": K.tolist(), "R": R.tolist(), "t": (-R @ c2w[:3, 3]).tolist()}


def nerfstudio(truth: dict, scale: float, width: int = WIDTH, height: int = HEIGHT) -> dict:
    """transforms.json at ``scale`` x the dataset's ``width x height``: top-level intrinsics,
    per-frame ones, and DROID's nested per-frame ``intrinsics``."""
    frames = []
    for i, (n, (K, c2w)) in enumerate(truth.items()):
        intr = {"fl_x": float(K[0, 0]) * scale, "fl_y": float(K[1, 1]) * scale, "cx": float(K[0, 2]) * scale,
                "cy": float(K[1, 2]) * scale, "w": width * scale, "h": height * scale, "k1": 0.0, "p1": 0.0}  # fmt: skip
        frame = {"file_path": f"images/{n}.png", "transform_matrix": opencv_to_opengl(c2w).tolist()}
        frames.append({**frame, "intrinsics": intr} if i == 0 else {**frame, **intr})
    return {"camera_model": "OPENCV", "frames": frames}


def convention_file(kind: str, truth: dict, folder: Path) -> Path:
    wrist = {"fx": 40.0, "fy": 40.0, "cx": 32.0, "cy": 24.0, "mount": "wrist"}
    if kind in ("gensplat", "gensplat-yaml"):
        data = {n: {"K": K.tolist(), "c2w": c2w.tolist(), "mount": "external"} for n, (K, c2w) in truth.items()}
        K = truth["front"][0]
        data["front"] = {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                         "c2w": truth["front"][1].tolist()}  # fmt: skip
        data["wrist"] = wrist
    elif kind == "opencv-w2c":
        data = {n: w2c(K, c2w) for n, (K, c2w) in truth.items()}
        R = torch.tensor(data["right"].pop("R"), dtype=torch.float64)
        data["right"]["rvec"] = rotation_matrix_to_axis_angle(R[None])[0].tolist()  # cv2.Rodrigues form
        data["right"]["t"] = [[v] for v in data["right"]["t"]]  # (3, 1) as cv2 returns it
        data["wrist"] = {**wrist, "cx": 31.5, "cy": 23.5}
    else:
        data = nerfstudio(truth, scale=2.0)
    path = folder / ("calibration.yaml" if kind == "gensplat-yaml" else "calibration.json")
    path.write_text(yaml.safe_dump(data) if kind == "gensplat-yaml" else json.dumps(data))
    return path


@pytest.mark.parametrize("kind", ["gensplat", "gensplat-yaml", "opencv-w2c", "nerfstudio"])
def test_each_convention_gives_the_same_cameras(kind, truth, tmp_path):
    root = tmp_path / "ds"
    features = write_info(root)
    source = convention_file(kind, truth, tmp_path)
    calibrate(root, source)  # the convention is recognised
    calib = load_calibration(features, root)
    for n, (K, c2w) in truth.items():
        torch.testing.assert_close(calib[n].K, K, rtol=0, atol=1e-9)
        torch.testing.assert_close(calib[n].c2w, c2w, rtol=0, atol=1e-9)
        assert calib[n].mount == "external"
    if kind != "nerfstudio":
        assert calib["wrist"].mount == "wrist" and calib["wrist"].c2w is None
        torch.testing.assert_close(calib["wrist"].K[:2, 2], torch.tensor([32.0, 24.0], dtype=torch.float64))
    # the feature's own calibration wins over the file
    info = {"camera.intrinsics": (truth["left"][0] * 0.5).tolist(), "camera.extrinsics": truth["left"][1].tolist()}
    features["observation.images.left"]["info"] = {**info, "camera.mount": "external"}
    torch.testing.assert_close(load_calibration(features, root)["left"].K[0, 0], truth["left"][0][0, 0] * 0.5)


def entry(truth, name="left", **fields) -> dict:
    K, c2w = truth[name]
    return {name: {"K": K.tolist(), "c2w": c2w.tolist(), **fields}}


def scaled(c2w: torch.Tensor, s: torch.Tensor) -> list:
    out = c2w.clone()
    out[:3, :3] = c2w[:3, :3] @ torch.diag(s.to(c2w.dtype))
    return out.tolist()


@pytest.mark.parametrize("case, message", [
    ("negative_focal", r"camera 'left', field K: .*focal lengths must be > 0"),
    ("scaled_rotation", r"camera 'left', field c2w: .*not orthonormal with det \+1"),
    ("mirrored_rotation", r"camera 'left', field c2w: .*not orthonormal with det \+1"),
    ("nan_pose", r"camera 'left', field c2w: values must be finite"),
    ("w2c_not_rotation", r"camera 'left', field R, t: .*not orthonormal"),
    ("unknown_camera", r"camera 'top' is not an image feature of the dataset \(its cameras: \['front', 'left'"),
    ("no_pose", r"camera 'left': an external camera needs its pose \(c2w\)"),
    ("typo", r"camera 'left': unknown field\(s\) \['ccx'\] for convention gensplat"),
    ("distortion", r"camera 'left': non-zero distortion .*undistort the images"),
    ("principal_point", r"camera 'left', field K: principal point \(640.0, 360.0\) lies outside .* 64x48 image"),
    ("not_json", r"calibration.json: not valid JSON"),
])  # fmt: skip
def test_bad_calibration_names_camera_and_field(case, message, truth, tmp_path):
    root = tmp_path / "ds"
    write_info(root)
    K, c2w = truth["left"]
    data = {
        "negative_focal": {"left": {"fx": -50.0, "fy": 50.0, "cx": 32.0, "cy": 24.0, "c2w": c2w.tolist()}},
        "scaled_rotation": entry(truth, c2w=scaled(c2w, torch.tensor([1.0, 1.0, 1.1]))),
        "mirrored_rotation": entry(truth, c2w=scaled(c2w, torch.tensor([1.0, 1.0, -1.0]))),
        "nan_pose": entry(truth, c2w=[[float("nan")] * 4] * 4),
        "w2c_not_rotation": {"left": {**w2c(K, c2w), "R": (2 * c2w[:3, :3]).tolist()}},
        "unknown_camera": entry(truth, "left") | {"top": entry(truth)["left"]},
        "no_pose": {"left": {"K": K.tolist()}},
        "typo": entry(truth, ccx=3.0),
        "distortion": entry(truth, dist=[[0.1, 0.0, 0.0, 0.0, 0.0]]),
        "principal_point": {"left": {"fx": 500.0, "fy": 500.0, "cx": 640.0, "cy": 360.0, "c2w": c2w.tolist()}},
    }.get(case)
    source = tmp_path / "calibration.json"
    source.write_text("{left: " if data is None else json.dumps(data))
    with pytest.raises(ValueError, match=message):
        calibrate(root, source)
    assert not calibration_path(root).exists()


def test_cli_prints_the_error_alone_and_keeps_internal_errors(truth, tmp_path, capsys, monkeypatch):
    root = tmp_path / "ds"
    write_info(root)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(entry(truth, "left", mount="ceiling")))
    assert main(["calibrate", "from-file", "--root", str(root), str(bad)]) == 2
    assert capsys.readouterr().err == (f"gensplat: error: {bad}: camera 'left': field 'mount' must be 'external' "
                                       "or 'wrist', got 'ceiling'\n")  # fmt: skip
    good = convention_file("opencv-w2c", truth, tmp_path)
    assert main(["calibrate", "from-file", "--root", str(root), str(good)]) == 0
    assert f"written to {calibration_path(root)}" in capsys.readouterr().out
    # a ValueError raised outside this project's code is a bug: its traceback is kept
    monkeypatch.setattr("gensplat_transforms.calibration.files.calibrate", lambda *a: json.loads("{"))
    with pytest.raises(json.JSONDecodeError):
        main(["calibrate", "from-file", "--root", str(root), str(good)])


def test_lerobot_source_uses_the_stored_calibration_and_the_dataset_is_untouched(truth, scene_dataset,
                                                                                 dataset_copy, tmp_path):
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed")
    os.environ["HF_HUB_OFFLINE"] = "1"
    from gensplat_lerobot import LeRobotSource

    repo = "local/uncalibrated"
    root = dataset_copy(scene_dataset(repo, episodes=1, frames=2, size=32))
    calibrated = LeRobotSource(root, repo)
    strip_calibration(root, NAMES)  # a dataset recorded without calibration
    shutil.rmtree(root / "depth")
    with pytest.raises(ValueError, match=r"a calibrated external camera; .* `gensplat calibrate estimate --root .*`"):
        LeRobotSource(root, repo)
    files = {f: f.read_bytes() for f in root.rglob("*") if f.is_file()}

    truth32 = {n: (calibrated.calibration[n].K, calibrated.calibration[n].c2w) for n in NAMES}
    source = tmp_path / "transforms.json"
    source.write_text(json.dumps(nerfstudio(truth32, 1.0, 32, 32)))
    assert main(["calibrate", "from-file", "--root", str(root), str(source)]) == 0
    assert {f: f.read_bytes() for f in root.rglob("*") if f.is_file() and "gensplat" not in f.parts} == files
    stored = LeRobotSource(root, repo)
    assert stored.camera_names == NAMES  # every calibrated external camera (no depth here)
    for i, n in enumerate(NAMES):
        torch.testing.assert_close(stored.cameras.K[i], truth32[n][0], rtol=0, atol=1e-9)
        torch.testing.assert_close(stored.cameras.c2w[i], truth32[n][1], rtol=0, atol=1e-9)
    # another calibration is another cache
    moved = nerfstudio({**truth32, "left": (truth32["left"][0], truth32["right"][1])}, 1.0, 32, 32)
    source.write_text(json.dumps(moved))
    calibrate(root, source)
    assert LeRobotSource(root, repo).fingerprint != stored.fingerprint
