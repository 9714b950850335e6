"""How a LeRobot dataset carries what GenSplat needs: calibration and depth.

LeRobot has no calibration fields, so they go into each image feature's ``info`` dict,
which LeRobot keeps in ``meta/info.json``:

* ``"camera.intrinsics"``: 3x3 nested list, pixels (pixel centres at +0.5);
* ``"camera.extrinsics"``: 4x4 nested list, OpenCV camera-to-world (static cameras);
* ``"camera.episodes"`` (optional, external cameras): ``{"<episode index>": 4x4}``, the
  camera-to-world of the episodes in which the camera stood elsewhere (e.g. DROID, whose
  cameras are placed anew for every episode); ``camera.extrinsics`` is then the pose of the
  other episodes, and may be absent when every episode has its own;
* ``"camera.mount"``: ``"external"`` or ``"wrist"`` (a wrist camera moves with the robot
  and is never reconstructed or perturbed);
* ``"camera.depth"`` (optional): the camera's depth maps are its depth sensor's own, not
  registered to the colour image: ``{"intrinsics": 3x3, "width", "height", "to_camera":
  4x4}``, the sensor's intrinsics at its maps' size and the rigid transform from its frame to
  the colour camera's (OpenCV axes; x_camera = to_camera @ x_sensor). Its depth is then
  registered to the colour camera when read (:mod:`.registration`).

A camera whose feature carries no calibration may take it from
``<root>/gensplat/calibration.json`` beside the dataset (written by ``gensplat calibrate``,
:mod:`.calibration`): ``{"format": "gensplat-calibration", "cameras": {name: info}}`` with
the same ``info`` entries, checked when read as ``gensplat calibrate`` checks its input. The
feature's own ``info`` wins where both exist (:func:`.calibration.load_calibration` reads both).

Metric depth of the external cameras is a sidecar beside the dataset (depth as a LeRobot
image feature would be fed to the policy as an extra camera):
``<root>/depth/<camera>/episode_<index:06d>.safetensors`` with one float16 tensor
``"depth"`` (T, H, W) in metres (camera z, 0 = invalid) and metadata ``format``,
``format_version``, ``camera``, ``episode_index``, ``num_frames``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors.torch import save_file

from ..core.atomic import atomic_write
from ..core.cameras import Cameras
from ..core.tensor_file import TensorFile

DEPTH_FORMAT = "gensplat-depth"
DEPTH_FORMAT_VERSION = "1"
IMAGE_KEY_PREFIX = "observation.images."
CALIBRATION_FORMAT = "gensplat-calibration"
#: beside the dataset, never inside it: ``<root>/<GENSPLAT_DIR>/`` holds settings, cache, calibration
GENSPLAT_DIR = "gensplat"
#: What GenSplat keeps in ``<root>/gensplat/``: its settings, the dataset's content record, the
#: calibration, the folders' digests and the cache; no output a user names may replace them.
GENSPLAT_OWNED = ("config.json", "dataset.json", "calibration.json", "digests.json", "cache")


@dataclass
class DepthSensor:
    """A camera's depth sensor, whose maps are not registered to its colour image: K (3, 3)
    at the maps' ``width`` x ``height``, ``to_camera`` (4, 4) from its frame to the colour
    camera's."""

    K: torch.Tensor
    width: int
    height: int
    to_camera: torch.Tensor

    def cameras(self, camera: Cameras) -> Cameras:
        """The sensor as one :class:`Cameras` beside ``camera`` (one colour camera)."""
        return Cameras(self.K[None].to(camera.c2w), self.pose(camera.c2w), self.width, self.height)

    def pose(self, c2w: torch.Tensor) -> torch.Tensor:
        """(..., 4, 4) camera-to-world of the sensor beside colour cameras of (..., 4, 4) poses
        ``c2w`` (each moved camera's sensor moves with it)."""
        return c2w @ torch.linalg.inv(self.to_camera.to(c2w))


@dataclass
class CameraCalibration:
    """Calibration of one named camera: K (3, 3), c2w (4, 4) or None, mount, its depth sensor
    where its depth maps are the sensor's own (None: registered to the colour image), and
    per-episode c2w (4, 4) by episode index, which replace ``c2w`` in their episodes."""

    name: str
    K: torch.Tensor
    c2w: torch.Tensor | None
    mount: str
    depth: DepthSensor | None = None
    episodes: dict[int, torch.Tensor] = field(default_factory=dict)

    def pose(self, episode: int | None = None) -> torch.Tensor | None:
        """(4, 4) camera-to-world in ``episode`` (None: the default pose ``c2w``)."""
        return self.episodes.get(episode, self.c2w)


def camera_info(K: torch.Tensor, c2w: torch.Tensor | None, mount: str, depth: DepthSensor | None = None,
                episodes: dict[int, torch.Tensor] | None = None) -> dict:
    """The ``info`` entries to put in an image feature or calibration.json (see the module docstring)."""
    if mount not in ("external", "wrist"):
        raise ValueError(f"camera.mount must be 'external' or 'wrist', got {mount!r}")
    info = {"camera.intrinsics": torch.as_tensor(K).tolist(), "camera.mount": mount}
    if c2w is not None:
        info["camera.extrinsics"] = torch.as_tensor(c2w).tolist()
    if depth is not None:
        info["camera.depth"] = {"intrinsics": depth.K.tolist(), "width": depth.width, "height": depth.height,
                                "to_camera": depth.to_camera.tolist()}  # fmt: skip
    if episodes:
        order = sorted(episodes)
        info["camera.episodes"] = dict(zip(map(str, order), torch.stack([torch.as_tensor(episodes[e]) for e in order]).tolist()))
    return info


def distinct_cameras(names, what: str = "--cameras") -> tuple[str, ...]:
    """``names`` as a tuple, or ``ValueError`` naming the cameras ``what`` (the option or field)
    gives more than once (a camera estimated against itself, a feature read twice, a camera
    reconstructed twice).

    Example:
        >>> distinct_cameras(["left", "right"])
        ('left', 'right')
    """
    names = tuple(names)
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"{what} names {twice} more than once: name each camera once")
    return names


def digests_path(root: str | Path) -> Path:
    """``<root>/gensplat/digests.json``: digests of the dataset's folders, with the file stats
    they were computed for (see ``gensplat_lerobot.source.files_digest``)."""
    return Path(root) / GENSPLAT_DIR / "digests.json"


def calibration_path(root: str | Path) -> Path:
    """``<root>/gensplat/calibration.json``: calibration kept beside the dataset."""
    return Path(root) / GENSPLAT_DIR / "calibration.json"


def image_sizes(features: dict) -> dict[str, tuple[int, int]]:
    """Camera name -> (width, height) of the image features of LeRobot ``meta.features``."""
    return {k[len(IMAGE_KEY_PREFIX) :]: (ft["shape"][1], ft["shape"][0])
            for k, ft in features.items() if k.startswith(IMAGE_KEY_PREFIX)}  # fmt: skip


def calibrated_cameras(calib: dict[str, CameraCalibration], names, width: int, height: int,
                       episode: int | None = None) -> Cameras:
    """Stack the named external cameras, at their poses in ``episode`` (None: their default
    poses), into one :class:`Cameras` batch."""
    missing = [n for n in names if n not in calib]
    if missing:
        raise ValueError(f"no calibration for camera(s) {missing}; calibrated: {sorted(calib)}")
    if any(calib[n].mount != "external" for n in names):
        raise ValueError(f"camera(s) {[n for n in names if calib[n].mount != 'external']} are not static external "
                         "cameras and cannot be reconstructed")  # fmt: skip
    unposed = [n for n in names if calib[n].pose(episode) is None]
    if unposed:
        raise ValueError(f"camera(s) {unposed} have no pose {'' if episode is None else f'in episode {episode} '}"
                         "(camera.extrinsics or camera.episodes of their calibration)")  # fmt: skip
    return Cameras(torch.stack([calib[n].K for n in names]), torch.stack([calib[n].pose(episode) for n in names]),
                   width, height)  # fmt: skip


def depth_path(root: str | Path, camera: str, episode: int) -> Path:
    return Path(root) / "depth" / camera / f"episode_{int(episode):06d}.safetensors"


def save_depth(root: str | Path, camera: str, episode: int, depth: torch.Tensor) -> Path:
    """Write a (T, H, W) metric depth sidecar atomically (float16; non-finite and negative
    values as 0, distances clamped to 60 km; float16 input is not copied to float32)."""
    if depth.ndim != 3:
        raise ValueError(f"save_depth: expected (T, H, W) depth, got {tuple(depth.shape)}")
    path = depth_path(root, camera, episode)
    meta = {"format": DEPTH_FORMAT, "format_version": DEPTH_FORMAT_VERSION, "camera": camera,
            "episode_index": str(int(episode)), "num_frames": str(depth.shape[0])}  # fmt: skip
    d = storable_depth(depth if depth.dtype == torch.float16 else depth.float())
    return atomic_write(path, lambda tmp: save_file({"depth": d.to(torch.float16).contiguous()}, tmp, metadata=meta))


def storable_depth(depth: torch.Tensor) -> torch.Tensor:
    """Metres as a sidecar stores them (same shape and dtype): non-finite and negative values
    as 0 (no depth), distances clamped to 60 km (float16 holds up to 65,504)."""
    return torch.nan_to_num(depth, nan=0.0, posinf=0.0, neginf=0.0).clamp(0, 6e4)


def load_depth(root: str | Path, camera: str, episode: int, frame: int | None = None) -> torch.Tensor:
    """Metric depth, float32: (T, 1, H, W), or (1, H, W) for one ``frame`` (only that one read)."""
    path = depth_path(root, camera, episode)
    if not path.exists():
        raise FileNotFoundError(f"no depth for camera {camera!r}, episode {episode}: {path} is missing")
    depth = open_depth(path)
    return depth[:].float()[:, None] if frame is None else depth[frame : frame + 1].float()


def open_depth(path: str | Path) -> DepthFile:
    """The ``"depth"`` tensor of a depth file, read frame by frame (``[t : t + 1]`` -> (1, H, W)
    float16); ``.get_shape()`` is (T, H, W). Raises ValueError naming the file when it is not
    a readable depth file."""
    return DepthFile(path)


class DepthFile:
    """A depth sidecar's ``"depth"`` tensor, its header checked once, its frames read with
    positioned reads when sliced (:class:`.tensor_file.TensorFile`: a worker opens one per
    sample at random, and mapping and unmapping three files costs it about 4x more than
    reading)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._file = TensorFile(self.path)
        except (OSError, ValueError) as e:  # both name the file
            raise ValueError(f"unreadable depth file: {e}") from e
        if self._file.metadata.get("format") != DEPTH_FORMAT or "depth" not in self._file:
            raise ValueError(f"{path}: not a GenSplat depth file")
        self.shape, dtype = self._file.shape("depth"), self._file.dtype("depth")
        if len(self.shape) != 3:
            raise ValueError(f"{path}: depth of shape {list(self.shape)}, expected (T, H, W)")
        if dtype != torch.float16:
            raise ValueError(f"{path}: depth of dtype {str(dtype).removeprefix('torch.')}, expected float16")

    def get_shape(self) -> tuple[int, int, int]:
        return self.shape

    def __getitem__(self, frames: slice) -> torch.Tensor:
        """(n, H, W) float16 frames ``frames`` (a slice with step 1, clamped to the file);
        ValueError when the file changed since it was opened."""
        if not isinstance(frames, slice) or frames.step not in (None, 1):
            raise ValueError(f"DepthFile: frames must be a slice with step 1, got {frames}")
        try:
            return self._file.read("depth", frames)
        except OSError as e:
            raise ValueError(f"unreadable depth file: {e}") from e
