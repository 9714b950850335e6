"""A LeRobot dataset as an :class:`~gensplat_transforms.cache.builder.EpisodeSource`, and as training
samples of the GenSplat model (:class:`LeRobotViews`)."""

from __future__ import annotations

import fnmatch
import hashlib
import importlib
import json
import logging
import os
import stat
from collections.abc import Iterator
from functools import cache, cached_property
from pathlib import Path

import torch
from torch.utils.data import Dataset

from gensplat_transforms.cache.format import check_sidecars
from gensplat_transforms.cache.store import DepthFiles
from gensplat_transforms.calibration.files import load_calibration
from gensplat_transforms.core.atomic import atomic_write_json, read_json_object, stat_stamp
from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.data.format import (
    IMAGE_KEY_PREFIX,
    calibrated_cameras,
    calibration_path,
    camera_info,
    depth_path,
    digests_path,
    distinct_cameras,
    load_depth,
    open_depth,
)
from gensplat_transforms.data.registration import register_depth
from gensplat_transforms.geometry import Views
from gensplat_transforms.geometry.model import PATCH_SIZE

log = logging.getLogger(__name__)

#: frames decoded per decoder call when a whole episode is read (8 frames of two 640x480
#: cameras: 59 MB of float32 images)
DECODE_CHUNK = 8


class LeRobotSource:
    """Views of the external cameras of a local LeRobot dataset, frame by frame.

    A camera's depth is its sidecar (:mod:`gensplat_transforms.data.format`), or else
    LeRobot's own depth-map feature of it, ``observation.images.<camera>_depth`` (``info``
    ``is_depth_map``, as LeRobot records a RealSense's depth; read in metres): a cache then
    stores a compressed copy, as there are no files to link.

    An episode's views carry the cameras at their poses in that episode
    (:meth:`episode_cameras`: the calibration's per-episode poses where it has them);
    :attr:`cameras` are those of episode 0, for what does not change between episodes (image
    size, intrinsics).

    Args:
        root: dataset root (holds ``meta/info.json``).
        repo_id: the dataset's repo id (offline use: any id matching the local copy).
        cameras: names of the external cameras to reconstruct (default: the external
            cameras that have depth, or all external cameras when none has); ValueError
            naming the dataset's cameras when one is not among them.
    """

    def __init__(self, root: str | Path, repo_id: str, cameras: tuple[str, ...] | str | None = None) -> None:
        self.root, self.repo_id = Path(root), repo_id
        info = read_info(self.root)
        cameras = (cameras,) if isinstance(cameras, str) else cameras
        check_cameras(self.root, cameras or (), info["features"])
        self.calibration = load_calibration(info["features"], self.root, info.get("total_episodes"))
        self.depth_features = {n: key for n in self.calibration
                               if _is_depth_map(info["features"].get(key := f"{IMAGE_KEY_PREFIX}{n}_depth"))}  # fmt: skip
        external = tuple(n for n, c in self.calibration.items() if c.mount == "external")
        with_depth = tuple(n for n in external if depth_path(self.root, n, 0).exists() or n in self.depth_features)
        self.camera_names = tuple(cameras) if cameras else (with_depth or external)
        if not self.camera_names:
            raise ValueError(
                f"{self.root}: GenSplat needs a calibrated external camera; calibrated external: "
                f"{list(external)}, image features: {image_names(info['features'])}. Estimate it from the frames with "
                f"`gensplat calibrate estimate --root {self.root}` (with depth; RGB only: add --model, or --fov and "
                "--baseline), or give it with `gensplat calibrate from-file "
                f"--root {self.root} FILE` (either is stored in {calibration_path(self.root)}, the dataset is not "
                "modified), or put it in the image features' info (gensplat_transforms.data.format)"
            )
        shape = info["features"][IMAGE_KEY_PREFIX + self.camera_names[0]]["shape"]  # (H, W, C)
        self.size = shape[1], shape[0]
        self.cameras = self.episode_cameras(0)
        #: cameras whose depth maps are their sensor's own: the sensor (in episode 0), registered on read
        self.sensors = self._sensors(self.cameras)
        self._dataset = None
        #: depth sidecars found to match the dataset: path -> its stat stamp when checked
        self._sidecars_checked: dict[Path, list[int]] = {}

    @cached_property
    def content(self) -> dict:
        """What the cache follows: episode and frame counts, fps, the reconstructed cameras in
        order with their features and calibration, per-episode poses included (the cache
        stores their Gaussians and cameras), and per folder holding their frames a digest of its files (so a re-recorded
        episode counts). Not the repo id: a cache is found by the data, whatever its name.
        Computed on first use."""
        info = read_info(self.root)
        calib = {n: self.calibration[n] for n in self.camera_names}
        cameras = [[n, info["features"][IMAGE_KEY_PREFIX + n], camera_info(c.K, c.c2w, c.mount, c.depth, c.episodes)]
                   for n, c in calib.items()]  # fmt: skip
        return {"episodes": info.get("total_episodes"), "frames": info.get("total_frames"), "fps": info.get("fps"),
                "cameras": cameras, "files": {d: files_digest(self.root, d, digests_path(self.root)) for d in self._content_dirs()}}  # fmt: skip

    @cached_property
    def fingerprint(self) -> str:
        """Keys the cache: a hash of :attr:`content`."""
        return hashlib.sha256(json.dumps(self.content, sort_keys=True).encode()).hexdigest()[:16]

    def _content_dirs(self) -> list[str]:
        """Folders (relative to the root) whose files hold this source's frames."""
        return ["data", *(f"videos/{IMAGE_KEY_PREFIX}{n}" for n in self.camera_names),
                *(f"depth/{n}" for n in self.camera_names),
                *(f"videos/{self.depth_features[n]}" for n in self.camera_names if n in self.depth_features)]  # fmt: skip

    def episode_cameras(self, episode: int) -> Cameras:
        """The reconstructed cameras at their poses in ``episode``."""
        return calibrated_cameras(self.calibration, self.camera_names, *self.size, episode=episode)

    def _sensors(self, cameras: Cameras) -> dict[str, Cameras]:
        """The depth sensors of the reconstructed ``cameras`` that have one, by camera name."""
        return {n: self.calibration[n].depth.cameras(cameras[i]) for i, n in enumerate(self.camera_names)
                if self.calibration[n].depth is not None}  # fmt: skip

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_dataset": None}

    @property
    def dataset(self):
        if self._dataset is None:
            from lerobot.datasets.lerobot_dataset import LeRobotDataset

            self._dataset = LeRobotDataset(self.repo_id, root=self.root, video_backend=video_backend(),
                                           depth_output_unit="m")  # fmt: skip
        return self._dataset

    def has_depth(self) -> bool:
        """Whether every reconstructed camera has depth: a sidecar (checked on episode 0) or a
        depth-map feature."""
        return all(depth_path(self.root, n, 0).exists() or n in self.depth_features for n in self.camera_names)

    @cached_property
    def _episodes(self) -> dict[str, list[int]]:
        return episode_table(self.dataset.meta)

    def _episode(self, field: str, episode: int) -> int:
        column = self._episodes[field]
        if not 0 <= episode < len(column):
            raise IndexError(f"{self.root}: episode {episode} is not in the dataset (episodes 0..{len(column) - 1})")
        return int(column[episode])

    def num_frames(self, episode: int) -> int:
        return self._episode("length", episode)

    def depth_files(self, episode: int) -> DepthFiles | None:
        """The episode's depth sidecars of the reconstructed cameras (None unless all exist and
        are registered to the colour images): a depth cache links them instead of storing a
        copy."""
        paths = tuple(depth_path(self.root, n, episode) for n in self.camera_names)
        found = all(p.exists() for p in paths) and not self.sensors
        return DepthFiles(paths, self.episode_cameras(episode), self.camera_names) if found else None

    def views(self, episode: int, frame: int) -> Views:
        n = self.num_frames(episode)
        if not 0 <= frame < n:
            raise IndexError(f"{self.root}: frame {frame} is not in episode {episode} (frames 0..{n - 1})")
        return self._views(episode, frame, self.dataset[self._episode("dataset_from_index", episode) + frame])

    def episode_views(self, episode: int) -> Iterator[Views]:
        """The :meth:`views` of every frame of ``episode`` in order, the same tensors, for
        building a cache: only the reconstructed cameras' videos (and depth-map videos) are
        decoded, ``DECODE_CHUNK`` frames per decoder call; a LeRobot item would decode every
        camera (the wrist's too) and seek for each frame. Features stored as images fall back
        to :meth:`views`."""
        n = self.num_frames(episode)
        keys = [IMAGE_KEY_PREFIX + name for name in self.camera_names]
        keys += [self.depth_features[name] for name in self.camera_names if name in self.depth_features]
        if not set(keys) <= set(self.dataset.meta.video_keys):
            yield from (self.views(episode, frame) for frame in range(n))
            return
        start = self._episode("dataset_from_index", episode)
        timestamps = [float(t) for t in self.dataset.hf_dataset[start : start + n]["timestamp"]]
        for first in range(0, n, DECODE_CHUNK):
            chunk = timestamps[first : first + DECODE_CHUNK]
            # LeRobot's own decode of an item's videos (its backend, tolerance and depth
            # dequantisation), for several timestamps at once (lerobot is pinned at 0.6.1)
            decoded = self.dataset.reader._query_videos({key: chunk for key in keys}, episode)
            decoded = {key: x.reshape(len(chunk), *x.shape[-3:]) for key, x in decoded.items()}
            for i in range(len(chunk)):
                yield self._views(episode, first + i, {key: x[i] for key, x in decoded.items()})

    def _views(self, episode: int, frame: int, item: dict) -> Views:
        """Views of ``frame`` from ``item``, which holds the reconstructed cameras' images and
        depth-map features as LeRobot items hold them."""
        images = torch.stack([_as_float(item[IMAGE_KEY_PREFIX + n]) for n in self.camera_names])
        cameras = self.episode_cameras(episode)
        sensors = self._sensors(cameras) if self.sensors else {}
        depths = []
        for i, n in enumerate(self.camera_names):
            path, where = depth_path(self.root, n, episode), self.root
            if path.exists():
                self._check_sidecar(DepthFiles((path,), cameras[i], (n,)), episode)
                depth, where = load_depth(self.root, n, episode, frame).float(), path
            elif n in self.depth_features:  # LeRobot's own, (1, H, W) in metres
                depth = item[self.depth_features[n]].float().reshape(1, *item[self.depth_features[n]].shape[-2:])
            else:
                return Views(images, cameras)  # RGB only: needs a model reconstructor
            sensor = sensors.get(n)
            want = tuple(images.shape[-2:]) if sensor is None else (sensor.height, sensor.width)
            if tuple(depth.shape[-2:]) != want:
                raise ValueError(
                    f"{where}: camera {n!r}, episode {episode}: depth maps of {depth.shape[-1]}x{depth.shape[-2]}, "
                    f"expected {want[1]}x{want[0]}, "
                    + ("the size its calibration's depth block gives" if sensor is not None else "its images' size: "
                       "maps of another size are a depth sensor's own; add its depth block to the calibration "
                       "(gensplat calibrate, docs/lerobot.md)")
                )  # fmt: skip
            depths.append(depth if sensor is None else register_depth(depth, sensor, cameras[i]))
        return Views(images, cameras, torch.stack(depths))

    def _check_sidecar(self, files: DepthFiles, episode: int) -> None:
        """ValueError naming the file when a depth sidecar's metadata names another camera,
        episode or frame count (:func:`~gensplat_transforms.cache.format.check_sidecars`) or it
        holds another number of frames than the episode has; checked again only when the file
        changes."""
        (path,) = files.paths
        stamp = stat_stamp(path.stat())
        if self._sidecars_checked.get(path) == stamp:
            return
        n = self.num_frames(episode)
        check_sidecars(files, episode, n)
        frames = open_depth(path).get_shape()[0]
        if frames != n:
            raise ValueError(f"{path}: {frames} frames of depth, the dataset's episode {episode} has {n}; import "
                             "the camera's depth again (gensplat import-depth --overwrite)")  # fmt: skip
        self._sidecars_checked[path] = stamp


class LeRobotViews(Dataset):
    """Every timestep of a local LeRobot dataset: its external cameras resized to ``size x size``,
    as training samples of the GenSplat model (``gensplat train-model --data lerobot``).

    A thin index over :class:`LeRobotSource`. Depth is present only where the dataset has depth
    sidecars (then ``TrueGeometryTeacher`` works); otherwise use ``Pi3Teacher``.
    """

    def __init__(
        self, root: str | Path, repo_id: str, size: int = 112, cameras: tuple[str, ...] | None = None
    ):
        if size % PATCH_SIZE:
            raise ValueError(f"LeRobotViews: size must be a multiple of {PATCH_SIZE}, got {size}")
        self.source, self.size = LeRobotSource(root, repo_id, cameras), size
        episodes = range(self.source.dataset.meta.total_episodes)
        self.index = [(e, t) for e in episodes for t in range(self.source.num_frames(e))]

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, i: int) -> Views:
        if not -len(self.index) <= i < len(self.index):
            raise IndexError(f"LeRobotViews: sample {i} is out of range; {self.source.root} has {len(self.index)} "
                             f"timesteps (0..{len(self.index) - 1})")  # fmt: skip
        return self.source.views(*self.index[i]).resized(self.size, self.size)


@cache
def video_backend() -> str:
    """LeRobot's video decoder on this machine: ``"torchcodec"`` when it loads (it needs FFmpeg's
    shared libraries), else ``"pyav"``. Chosen quietly: asked to choose, LeRobot logs every
    library torchcodec failed to load, with its traceback, before it falls back to PyAV."""
    try:
        importlib.import_module("torchcodec")
    except (ImportError, OSError, RuntimeError):
        return "pyav"
    return "torchcodec"


def episode_table(meta) -> dict[str, list[int]]:
    """Every episode's ``episode_index``, ``length`` and ``dataset_from_index`` from a
    ``LeRobotDatasetMetadata``, in one read (3 ms for 76k rows, where a lookup per episode
    takes 0.1-2 ms and iterating a column 0.5 s)."""
    return meta.episodes.select_columns(["episode_index", "length", "dataset_from_index"]).to_dict()


def _is_depth_map(feature: dict | None) -> bool:
    """Whether a LeRobot feature is a depth map (LeRobot's own test, on ``info.json``)."""
    if not feature:
        return False
    info, video = feature.get("info") or {}, feature.get("video_info") or {}
    return bool(info.get("is_depth_map") or info.get("video.is_depth_map") or video.get("video.is_depth_map"))


def read_info(root: Path) -> dict:
    """``meta/info.json`` of a local LeRobot dataset (FileNotFoundError when missing,
    ValueError when it is not a JSON object with ``features``)."""
    path = root / "meta" / "info.json"
    if not path.is_file():
        raise FileNotFoundError(f"{root}: not a local LeRobot dataset ({path} does not exist)")
    info = read_json_object(path)
    if not isinstance(info.get("features"), dict):
        raise ValueError(  # noqa: TRY004 (the file's content)
            f"{path}: not a LeRobot dataset's info (unreadable, or no 'features' object); give the root of a "
            "LeRobot dataset, the folder holding meta/info.json"
        )
    return info


def image_names(features: dict) -> list[str]:
    """The camera names of a LeRobot dataset's image features (``observation.images.<name>``)."""
    return [k[len(IMAGE_KEY_PREFIX) :] for k in features if k.startswith(IMAGE_KEY_PREFIX)]


def check_cameras(root: str | Path, cameras, features: dict | None = None) -> None:
    """ValueError naming the dataset's cameras when one of ``cameras`` is not among them, or
    naming one given twice (``features``: those of its ``info.json``, read when not given)."""
    distinct_cameras(cameras)
    names = image_names(read_info(Path(root))["features"] if features is None else features)
    unknown = [c for c in cameras if c not in names]
    if unknown:
        raise ValueError(f"{root}: no camera(s) {unknown}; its cameras: {names}; name cameras among them")


def files_digest(root: Path, folder: str, memo: Path | None = None, sample: int = 16384) -> str:
    """SHA-256 over the files under ``root/folder``: each file's relative path, size, and its
    first and last ``sample`` bytes (cheap on large video files; an edit that keeps the size
    and both ends is not noticed). A missing folder counts as empty; in a depth folder
    (``depth/<camera>``) only the sidecars count (``episode_*.safetensors``, not a note beside them).

    With ``memo`` (a JSON file, written atomically where its folder exists), a folder whose files all
    have the paths, sizes, modification times and inodes they had when its digest was last
    computed gets that digest back without a file being read (one ``stat`` per file instead
    of two reads: what makes a folder of many thousands of depth files quick to check)."""
    files = _regular_files(root, folder)
    listing = hashlib.sha256(json.dumps([[rel, *stat_stamp(st)] for _, rel, st in files]).encode()).hexdigest()
    memos = read_json_object(memo) if memo is not None else {}
    known = memos.get(folder)
    if isinstance(known, dict) and known.get("listing") == listing and isinstance(known.get("digest"), str):
        return known["digest"]
    h = hashlib.sha256()
    for path, rel, st in files:
        h.update(f"{rel}\0{st.st_size}\0".encode())
        with open(path, "rb") as fh:
            h.update(fh.read(sample))
            if st.st_size > sample:
                fh.seek(max(sample, st.st_size - sample))
                h.update(fh.read(sample))
    digest = h.hexdigest()
    if memo is not None and memo.parent.is_dir():
        try:
            atomic_write_json(memo, {**memos, folder: {"listing": listing, "digest": digest}})
        except (OSError, ValueError) as e:  # a read-only folder, a folder in the way
            log.info("cannot write %s (%s): the next check reads the files again", memo, e)
    return digest


def _regular_files(root: Path, folder: str) -> list[tuple[str, str, os.stat_result]]:
    """(path, path relative to ``root``, stat) of the files under ``root/folder`` (links to
    files followed, links to folders not), in ``pathlib`` path order; plain strings, which
    make a folder of many thousands of files several times quicker to list than ``Path``.
    Temporary files of :func:`.atomic.atomic_write` (``.<name>.<hex>.tmp``, left behind by a
    writer that was killed) are not the dataset's content, nor anything but the sidecars of a
    depth folder."""
    base, prefix, found = str(root / folder), Path(folder).as_posix(), []
    sidecars = Path(folder).parts[:1] == ("depth",)
    for top, folders, names in os.walk(base):
        if sidecars:
            folders.clear()
            names = fnmatch.filter(names, "episode_*.safetensors")
        for name in names:
            if name.startswith(".") and name.endswith(".tmp"):
                continue
            path = os.path.join(top, name)
            try:
                st = os.stat(path)
            except OSError:  # e.g. a broken link
                continue
            if stat.S_ISREG(st.st_mode):
                found.append((path, prefix + path[len(base) :], st))
    return sorted(found, key=lambda f: f[1].split("/"))


def _as_float(image: torch.Tensor) -> torch.Tensor:
    return image.float() / 255 if image.dtype == torch.uint8 else image.float()
