"""A depth sensor's own maps registered to the colour camera (LeRobot records a RealSense's
depth unregistered): the function against the scene's truth, its hard cases, the
calibration's ``depth`` block, and the LeRobot source reading registered depth."""

import json
import os
import shutil
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch
import yaml
from helpers import strip_calibration, write_image_features

from gensplat_transforms.cache.depth_codec import depth_from_words
from gensplat_transforms.calibration.files import calibrate, load_calibration
from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.data.format import DepthSensor, save_depth
from gensplat_transforms.data.registration import register_depth
from gensplat_transforms.data.scenes import TabletopScene, default_cameras

WIDTH, HEIGHT = 160, 120


def sensor_beside(
    camera: Cameras, width: int, height: int, fov: float = 0.75
) -> tuple[Cameras, torch.Tensor]:
    """A depth sensor ``fov`` x the camera's focal length (a wider view), at ``width x height``,
    15 mm to its side and turned 1.1 degrees, as a RealSense's; and its to_camera (4, 4)."""
    K = camera.K.clone()
    K[:, 0] *= fov * width / camera.width
    K[:, 1] *= fov * height / camera.height
    K[:, 0, 2], K[:, 1, 2] = width / 2, height / 2
    a = torch.tensor(0.02, dtype=torch.float64)
    to_camera = torch.eye(4, dtype=torch.float64)
    to_camera[:3, :3] = torch.tensor(
        [[a.cos(), 0, a.sin()], [0, 1, 0], [-a.sin(), 0, a.cos()]], dtype=torch.float64
    )
    to_camera[0, 3] = -0.015
    return Cameras(K, camera.c2w @ torch.linalg.inv(to_camera), width, height), to_camera


@pytest.mark.parametrize(("width", "height"), [(WIDTH, HEIGHT), (80, 60)])
def test_registered_depth_is_the_colour_cameras_depth(width, height):
    """The sensor's map moved into the colour camera matches the depth the colour camera
    sees (to the depth change across a pixel), where the raw map is 16 cm off; a sensor of
    half the resolution still covers the view (each pixel's footprint fills 2x2 pixels)."""
    camera = default_cameras(WIDTH, HEIGHT)[:1]
    sensor, _ = sensor_beside(camera, width, height)
    scene = TabletopScene(5)
    raw, truth = scene.render(sensor)[1][0, 0], scene.render(camera)[1][0, 0]
    registered = register_depth(raw, sensor, camera)
    assert registered.shape == (HEIGHT, WIDTH) and registered.dtype == raw.dtype
    both = (registered > 0) & (truth > 0)
    assert both.float().mean() > 0.97
    error = (registered - truth)[both].abs()
    assert error.median() < 0.006 and error.quantile(0.95) < 0.03  # measured 2.9 / 11 mm at 160x120
    if (width, height) == (WIDTH, HEIGHT):
        assert (raw - truth).abs().median() > 0.1  # what using the raw map would cost


def test_hard_depth_values_are_skipped_and_nothing_non_finite_comes_out():
    camera = default_cameras(WIDTH, HEIGHT)[:1]
    sensor, _ = sensor_beside(camera, WIDTH, HEIGHT)
    depth = torch.full((3, HEIGHT, WIDTH), 1.5)
    depth[0, :10] = float("nan")
    depth[0, 10:20] = float("inf")
    depth[0, 20:30] = -1.0
    depth[1] = 0.0  # nothing measured
    depth[2, :, :40] = 1e-7  # closer than the sensors' baseline: behind or beside the colour camera
    depth[2, :, 40:80] = 1e5
    out = register_depth(depth, sensor, camera)
    assert out.shape == (3, HEIGHT, WIDTH) and torch.isfinite(out).all() and (out >= 0).all()
    assert (out[0] > 0).float().mean() > 0.5 and not out[1].any() and out[2].max() < 1.01e5
    with pytest.raises(ValueError, match="depth of shape"):
        register_depth(depth[:, :10], sensor, camera)
    with pytest.raises(ValueError, match="one sensor and one camera"):
        register_depth(depth, sensor, default_cameras(WIDTH, HEIGHT)[:2])


def test_each_depth_pixel_fills_the_colour_pixels_its_footprint_covers_and_the_nearest_wins():
    """A sensor at the camera's pose with half its resolution: depth pixel (r, c) covers
    colour pixels 2r..2r+1 x 2c..2c+1 exactly. A nearer footprint shifted over a farther one
    wins where they overlap. Integer and half-precision maps come back as float32 and
    float16."""
    K = torch.tensor([[40.0, 0, 16], [0, 40, 12], [0, 0, 1]], dtype=torch.float64)
    camera = Cameras(K[None], torch.eye(4, dtype=torch.float64)[None], 32, 24)
    sensor = Cameras((K * torch.tensor([[0.5], [0.5], [1]], dtype=torch.float64))[None], camera.c2w, 16, 12)
    depth = torch.rand(2, 12, 16, generator=torch.Generator().manual_seed(0)) + 0.5
    out = register_depth(depth, sensor, camera)
    assert torch.equal(out, depth.repeat_interleave(2, -2).repeat_interleave(2, -1))
    assert register_depth(depth.half(), sensor, camera).dtype == torch.float16
    as_int = register_depth((depth * 1000).to(torch.int32), sensor, camera)
    assert as_int.dtype == torch.float32 and torch.equal(
        as_int[:, ::2, ::2], (depth * 1000).to(torch.int32).float()
    )
    # the sensor 1 cm to the camera's right sees a wall at 0.5 m before one at 1 m: in the
    # camera its footprints shift 40 px/m x 0.01 m / z, 0.8 px at 0.5 m, 0.4 px at 1 m, so the
    # near wall ends at u = 16.8, over the far wall's start (16.4): colour pixel 16 is both's
    moved = Cameras(sensor.K, sensor.c2w.clone(), 16, 12)
    moved.c2w[0, 0, 3] = 0.01
    wall = torch.ones(12, 16)
    wall[:, :8] = 0.5
    out = register_depth(wall, moved, camera)
    expected = torch.tensor([0.0] + [0.5] * 16 + [1.0] * 15)  # column 0's centre (0.5) is left of 0.8
    assert torch.equal(out, expected.expand(24, 32))


def calibration_file(folder, cameras: Cameras, names, sensors: dict | None = None):
    """A ``gensplat`` calibration file of ``cameras``, with depth blocks ``sensors`` (name -> (K,
    width, height, to_camera))."""
    data = {n: {"K": cameras.K[i].tolist(), "c2w": cameras.c2w[i].tolist()} for i, n in enumerate(names)}
    for n, (K, w, h, to_camera) in (sensors or {}).items():
        data[n]["depth"] = {"K": K.tolist(), "width": w, "height": h, "to_camera": to_camera.tolist()}
    path = folder / "calibration.json"
    path.write_text(json.dumps(data))
    return path


def test_the_calibrations_depth_block_is_checked_stored_and_read_back(tmp_path):
    cameras = default_cameras(WIDTH, HEIGHT)[:2]
    sensor, to_camera = sensor_beside(cameras[0:1], 80, 60)
    features = write_image_features(tmp_path, ("left", "right"), WIDTH, HEIGHT)
    good = {"left": (sensor.K[0], 80, 60, to_camera)}
    calibrate(tmp_path, calibration_file(tmp_path, cameras, ("left", "right"), good))
    calib = load_calibration(features, tmp_path)
    assert calib["right"].depth is None
    depth = calib["left"].depth
    assert isinstance(depth, DepthSensor) and (depth.width, depth.height) == (80, 60)
    torch.testing.assert_close(depth.K, sensor.K[0])
    torch.testing.assert_close(depth.to_camera, to_camera)
    torch.testing.assert_close(depth.cameras(cameras[0:1]).c2w, sensor.c2w)
    # opencv-w2c: the sensor's pixel centres at integers too (a RealSense's ppx, ppy), in YAML
    R = cameras.c2w[:, :3, :3].transpose(1, 2)
    t = -(R @ cameras.c2w[:, :3, 3:])[..., 0]
    K_cv = sensor.K[0].clone()
    K_cv[:2, 2] -= 0.5
    entries = {n: {"K": (cameras.K[i] - torch.tensor([[0, 0, 0.5], [0, 0, 0.5], [0, 0, 0]])).tolist(),
                   "R": R[i].tolist(), "t": t[i].tolist()} for i, n in enumerate(("left", "right"))}  # fmt: skip
    entries["left"]["depth"] = {"fx": float(K_cv[0, 0]), "fy": float(K_cv[1, 1]), "cx": float(K_cv[0, 2]),
                                "cy": float(K_cv[1, 2]), "width": 80, "height": 60, "to_camera": to_camera.tolist()}  # fmt: skip
    (tmp_path / "opencv.yaml").write_text(yaml.safe_dump(entries))
    calibrate(tmp_path, tmp_path / "opencv.yaml")
    torch.testing.assert_close(load_calibration(features, tmp_path)["left"].depth.K, sensor.K[0])
    bent = to_camera.clone()
    bent[0, 0] = 2.0
    cases = {
        "needs K \\(or fx, fy, cx, cy\\), width, height and to_camera": {"K": sensor.K[0].tolist(), "width": 80, "height": 60},
        "unknown \\['scale'\\]": {"K": sensor.K[0].tolist(), "width": 80, "height": 60, "to_camera": to_camera.tolist(),
                                   "scale": 1},
        "positive whole numbers": {"K": sensor.K[0].tolist(), "width": 80.5, "height": 60,
                                   "to_camera": to_camera.tolist()},
        "field to_camera: .*orthonormal": {"K": sensor.K[0].tolist(), "width": 80, "height": 60,
                                           "to_camera": bent.tolist()},
        "expected a mapping": [1, 2],
    }  # fmt: skip
    for message, block in cases.items():
        path = calibration_file(tmp_path, cameras, ("left", "right"))
        data = json.loads(path.read_text())
        data["left"]["depth"] = block
        path.write_text(json.dumps(data))
        with pytest.raises(ValueError, match=f"camera 'left', field depth.*{message}"):
            calibrate(tmp_path, path)


def test_lerobot_source_registers_a_sensors_own_depth(scene_dataset, dataset_copy, tmp_path):
    """A dataset without calibration whose depth sidecars are the sensors' own maps (40x30 of
    64x64 frames): calibrated with depth blocks, its views carry the colour cameras' depth,
    the sidecars are not linked (the cache stores the registered copy), the blocks are part
    of the cache's fingerprint, and import-depth takes maps of the sensor's size."""
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed")
    os.environ["HF_HUB_OFFLINE"] = "1"
    from gensplat_lerobot import LeRobotSource, enable_gensplat, load_settings, prepare
    from gensplat_lerobot.dataset import dataset_cache, make_reconstructor
    from gensplat_lerobot.depth import import_dataset_depth

    from gensplat_transforms.cache.builder import SceneEpisodes
    from gensplat_transforms.transform import GenSplatConfig

    repo, names = "local/unregistered", ("left", "right")
    root = dataset_copy(scene_dataset(repo, episodes=1, frames=2, size=64))
    source = SceneEpisodes(num_episodes=1, num_frames=2, size=64)  # what was recorded
    cameras = LeRobotSource(root, repo).cameras
    strip_calibration(root)  # recorded without calibration, as LeRobot records
    sensors = {n: sensor_beside(cameras[i : i + 1], 40, 30) for i, n in enumerate(names)}
    for i, n in enumerate(names):
        frames = [source.scene(0, t).render(sensors[n][0])[1][0, 0] for t in range(2)]
        shutil.rmtree(root / "depth" / n)
        save_depth(root, n, 0, torch.stack(frames))
    calibrate(root, calibration_file(tmp_path, cameras, names))
    without_blocks = LeRobotSource(root, repo)
    assert not without_blocks.sensors and without_blocks.depth_files(0) is not None
    with pytest.raises(
        ValueError, match=r"camera 'left', episode 0: depth maps of 40x30, expected 64x64, .*depth block"
    ):
        without_blocks.views(0, 1)
    blocks = {n: (s.K[0], 40, 30, to_camera) for n, (s, to_camera) in sensors.items()}
    calibrate(root, calibration_file(tmp_path, cameras, names, blocks))
    lerobot_source = LeRobotSource(root, repo)
    assert set(lerobot_source.sensors) == set(names) and lerobot_source.depth_files(0) is None
    assert lerobot_source.fingerprint != without_blocks.fingerprint
    views = lerobot_source.views(0, 1)
    truth = source.render(0, 1)[1][:2]
    assert views.depths.shape == truth.shape
    both = (views.depths > 0) & (truth > 0)
    assert both.float().mean() > 0.9 and (views.depths - truth)[both].abs().median() < 0.02
    stats = prepare(root, repo, GenSplatConfig(probability=1.0), progress=False)
    assert load_settings(root)[1]["name"] == "rgbd" and stats[0].bytes_per_timestep > 200  # a stored copy
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    plugged = enable_gensplat(LeRobotDataset(repo, root=root))  # depth-map features would follow the sensors
    assert set(plugged.gensplat.depth_sensors) == set(names)
    assert (
        plugged.gensplat.depth_sensors["left"].width == 40
        and torch.isfinite(plugged[1]["observation.images.left"]).all()
    )
    (words, coded), _ = dataset_cache(
        root, make_reconstructor({"name": "rgbd"}), lerobot_source
    ).read_depth_words(0, 1)
    torch.testing.assert_close(depth_from_words(words, coded)[:, None], views.depths, rtol=5e-4, atol=0)
    np.save(tmp_path / "ep0.npy", torch.stack([source.scene(0, t).render(sensors["left"][0])[1][0, 0]
                                               for t in range(2)]).numpy())  # fmt: skip
    imported = import_dataset_depth(root, repo, "left", str(tmp_path / "ep{episode}.npy"), units="m",
                                    overwrite=True, progress=False)  # fmt: skip
    assert list(imported) == [0]
    wrong = {n: (s.K[0], 80, 60, to_camera) for n, (s, to_camera) in sensors.items()}
    calibrate(root, calibration_file(tmp_path, cameras, names, wrong))
    with pytest.raises(
        ValueError, match=r"depth maps of 40x30, expected 80x60, the size its calibration's depth block"
    ):
        LeRobotSource(root, repo).views(0, 0)


def test_random_rigs_never_write_outside_the_image_or_leave_non_finite_depth(tmp_path):
    """Sensors and cameras of 1 to 40 pixels a side, focal lengths from 0.01 to 10^4 px, any
    rotation, baselines from 1 mm to 10 m, depths over 10 decades with NaN and Inf: the
    compiled kernel, recompiled with numba's bounds checks on, never indexes outside its
    arrays, and every value out is finite and >= 0."""
    script = textwrap.dedent("""
        import torch
        from gensplat_transforms.core.cameras import Cameras
        from gensplat_transforms.data.registration import register_depth
        from gensplat_transforms.core.rotations import quat_to_rotmat
        g = torch.Generator().manual_seed(0)
        def size():
            return int(torch.randint(1, 41, (1,), generator=g)), int(torch.randint(1, 31, (1,), generator=g))
        def K(w, h):
            f = 10 ** (6 * torch.rand(1, generator=g).item() - 2)
            return torch.tensor([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1]], dtype=torch.float64)[None]
        for _ in range(200):
            (w, h), (W, H) = size(), size()
            pose = torch.eye(4, dtype=torch.float64)
            q = torch.randn(4, generator=g, dtype=torch.float64)
            pose[:3, :3] = quat_to_rotmat(q / q.norm())
            pose[:3, 3] = torch.randn(3, generator=g, dtype=torch.float64) * 10 ** (4 * torch.rand(1, generator=g).item() - 3)
            depth = torch.exp(5 * torch.randn(2, h, w, generator=g))
            depth[0, 0, 0], depth[1, -1, -1] = float("nan"), float("inf")
            out = register_depth(depth, Cameras(K(w, h), pose[None], w, h),
                                 Cameras(K(W, H), torch.eye(4, dtype=torch.float64)[None], W, H))
            assert out.shape == (2, H, W) and torch.isfinite(out).all() and (out >= 0).all()
        print("ok")
    """)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    env |= {"NUMBA_BOUNDSCHECK": "1", "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=600,
                          check=False)  # fmt: skip
    assert done.returncode == 0 and done.stdout.split() == ["ok"], done.stderr
