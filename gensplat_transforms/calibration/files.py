"""Camera calibration for a LeRobot dataset whose image features carry none (``gensplat
calibrate``): read from a file in one of three conventions, validated, and stored beside the
dataset in ``<root>/gensplat/calibration.json`` (:func:`.data.format.calibration_path`);
the dataset itself, ``meta/info.json`` included, is never modified.

Conventions of the input file (JSON, or YAML when it ends in ``.yaml``/``.yml``):

* ``gensplat``: ``{camera: {"K": 3x3 or "fx", "fy", "cx", "cy", "c2w": 4x4, "mount"}}``,
  the dataset format's own: OpenCV camera axes (x right, y down, looking along +z),
  camera-to-world, pixel centres at +0.5.
* ``opencv-w2c``: ``{camera: {"K" or "fx".., "R": 3x3 or "rvec": 3 (Rodrigues), "t": 3,
  "mount"}}``, world-to-camera as ``cv2.calibrateCamera``/``cv2.solvePnP`` return it
  (x_cam = R x_world + t); OpenCV puts pixel centres at integers, so cx, cy gain 0.5 here.
* ``nerfstudio``: a ``transforms.json``: ``frames``, each with ``file_path`` (its file name
  without extension names the camera) and ``transform_matrix`` (camera-to-world with OpenGL
  axes: y up, looking along -z; y and z are flipped to OpenCV's), intrinsics ``fl_x``,
  ``fl_y``, ``cx``, ``cy``, ``w``, ``h`` in the frame, in its ``intrinsics``, or at the top.

``mount`` is ``external`` (default) or ``wrist`` (no c2w needed). ``width``/``height``
(nerfstudio: ``w``/``h``), when given and not the dataset's image size, rescale K to it.
Distortion coefficients must be zero: GenSplat renders pinhole views of undistorted images.
Focal lengths must give a field of view 2 atan(size / 2f) within :data:`FOV_RANGE` (fx on
the width, fy on the height; 1 to 179 degrees: f from 0.0044 to 57 times the size), and K
no skew. A file is at most :data:`MAX_FILE_BYTES`, UTF-8, and a YAML file has no aliases and
at most :data:`MAX_YAML_DEPTH` levels of nesting.

``depth`` (``gensplat`` and ``opencv-w2c``; optional): the camera's depth maps are its depth
sensor's own, not registered to the colour image (LeRobot 0.6 records a RealSense's depth so):
``{"K" or "fx".., "width", "height", "to_camera": 4x4}``, the sensor's intrinsics at its
maps' size (``opencv-w2c``: pixel centres at integers, as for the colour camera) and the
rigid transform from the sensor's frame to the colour camera's (OpenCV axes). With
pyrealsense2: ``depth_profile.get_intrinsics()`` and ``depth_profile.get_extrinsics_to(
color_profile)`` (its ``rotation`` is column-major: R = reshape(3, 3).T, t = translation).
The depth is then registered to the colour camera when read (:mod:`.registration`).

``episodes`` (``gensplat`` and ``opencv-w2c``; optional, external cameras): the camera's pose
per episode, for cameras placed anew between episodes: ``{index: {"c2w": 4x4}}``, or
``{index: {"R" or "rvec", "t"}}`` in ``opencv-w2c``, indices as in the dataset's
``episode_index``. The camera's own pose (``c2w``; ``R``, ``t``) is then the pose of the
episodes not listed, and may be left out when every episode of the dataset is listed.

:func:`calibrate_from_features` reads the per-episode poses from the dataset's own
``camera_extrinsics.<camera>`` features instead, as DROID's LeRobot port stores them
(:func:`xyz_rpy_pose`).

:func:`load_calibration` gives a dataset's cameras: its features' own calibration, else that of
calibration.json, checked as an input file is.
"""

from __future__ import annotations

import json
import math
from collections.abc import Hashable
from pathlib import Path

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix

from ..core.atomic import atomic_write_json
from ..core.cameras import Cameras, focal_from_fov, opengl_to_opencv
from ..data.format import (
    CALIBRATION_FORMAT,
    IMAGE_KEY_PREFIX,
    CameraCalibration,
    DepthSensor,
    calibration_path,
    camera_info,
    distinct_cameras,
    image_sizes,
)
from ..data.outputs import gensplat_folder

CONVENTIONS = ("auto", "gensplat", "opencv-w2c", "nerfstudio")
_INTRINSICS = ("K", "fx", "fy", "cx", "cy")
_FIELDS = {"gensplat": {*_INTRINSICS, "c2w", "mount", "width", "height", "depth", "episodes"},
           "opencv-w2c": {*_INTRINSICS, "R", "rvec", "t", "mount", "width", "height", "depth", "episodes"}}  # fmt: skip
_POSE_FIELDS = {"gensplat": {"c2w"}, "opencv-w2c": {"R", "rvec", "t"}}
_SENSOR_FIELDS = {*_INTRINSICS, "width", "height", "to_camera"}
_DISTORTION = ("dist", "k1", "k2", "k3", "k4", "p1", "p2")
#: calibration.json's ``info`` keys (:func:`.data.format.camera_info`) as the gensplat convention's
_STORED = {"camera.intrinsics": "K", "camera.extrinsics": "c2w", "camera.mount": "mount",
           "camera.depth": "depth", "camera.episodes": "episodes"}  # fmt: skip
MAX_FILE_BYTES = 1_000_000
#: levels of nesting a YAML calibration file may have (it needs 6); PyYAML scans deep nesting in
#: quadratic time (60 kB of brackets ran past a minute)
MAX_YAML_DEPTH = 32
#: degrees: a focal length outside it is a unit or typing mistake (black or degenerate views)
FOV_RANGE = (1.0, 179.0)
#: ``<POSE_FEATURE><camera>``: a float feature (6,) x, y, z, roll, pitch, yaw (DROID's LeRobot port)
POSE_FEATURE = "camera_extrinsics."
#: metres and radians: how far a pose feature may vary within one episode
POSE_TOLERANCE = 1e-4


def calibrate(root: str | Path, source: str | Path, convention: str = "auto") -> dict[str, CameraCalibration]:
    """Read ``source`` (see the module docstring), check it against the dataset at ``root``
    and write ``<root>/gensplat/calibration.json``. Returns the cameras written.

    Raises ``ValueError`` naming the camera and field of anything invalid, and
    ``FileNotFoundError`` when ``root`` is not a LeRobot dataset or ``source`` is missing.
    """
    info = _info(root)
    cameras = read_calibration(source, image_sizes(info["features"]), convention, info.get("total_episodes"))
    return _write(root, source, info["features"], cameras)


def calibrate_from_features(root: str | Path, intrinsics: str | Path | None = None, fov: float | None = None,
                            focal: float | None = None, cameras=None) -> dict[str, CameraCalibration]:
    """Write ``<root>/gensplat/calibration.json`` with each external camera's pose per episode
    from the dataset's ``camera_extrinsics.<camera>`` features (:func:`xyz_rpy_pose`, the
    first frame of each episode) and intrinsics from exactly one of ``intrinsics`` (a
    calibration file in a convention of the module docstring; only K is read), ``fov`` (the
    horizontal field of view in degrees) or ``focal`` (pixels; both square pixels, principal
    point at the image centre). ``cameras``: those to calibrate (default: every camera with
    such a feature whose name does not contain "wrist"). Returns the cameras written.

    Raises ``ValueError`` when a pose changes within an episode (by more than
    :data:`POSE_TOLERANCE`), and as :func:`calibrate` does for anything invalid."""
    root = Path(root)
    info = _info(root)
    features, sizes = info["features"], image_sizes(info["features"])
    posed = [n for n in sizes if POSE_FEATURE + n in features]
    names = list(distinct_cameras(cameras or [n for n in posed if "wrist" not in n]))
    if not names or any(n not in posed for n in names):
        raise ValueError(f"{root}: camera(s) {[n for n in names if n not in posed] or names} have no "
                         f"{POSE_FEATURE}<camera> feature of x, y, z, roll, pitch, yaw (cameras with one: {posed})")  # fmt: skip
    shapes = {n: features[POSE_FEATURE + n].get("shape") for n in names}
    if any(list(shape or ()) != [6] for shape in shapes.values()):
        raise ValueError(f"{root}: {POSE_FEATURE}<camera> features must have shape (6,): {shapes}")
    given = _given_intrinsics(names, sizes, intrinsics, fov, focal)
    poses = _feature_poses(root, [POSE_FEATURE + n for n in names])
    entries = {n: {**given[n], "episodes": {e: {"c2w": xyz_rpy_pose(v).tolist()} for e, v in poses[POSE_FEATURE + n].items()}}
               for n in names}  # fmt: skip
    found = _cameras(root / "data", entries, sizes, "gensplat", info.get("total_episodes"))
    return _write(root, root / "data", features, found)


def xyz_rpy_pose(xyz_rpy) -> torch.Tensor:
    """(4, 4) camera-to-world of a (6,) pose feature x, y, z, roll, pitch, yaw (metres, radians):
    R = Rz(yaw) Ry(pitch) Rx(roll) (extrinsic x-y-z Euler angles, as ``scipy``'s
    ``Rotation.from_euler("xyz", ...)``), OpenCV camera axes (x right, y down, looking along
    +z), in the robot base frame: DROID's ``camera_extrinsics``."""
    x, y, z, roll, pitch, yaw = (float(v) for v in xyz_rpy)
    (cr, sr), (cp, sp), (cy, sy) = ((math.cos(a), math.sin(a)) for a in (roll, pitch, yaw))
    return torch.tensor([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr, x],
                         [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr, y],
                         [-sp, cp * sr, cp * cr, z],
                         [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64)  # fmt: skip


def _info(root: Path) -> dict:
    """``meta/info.json`` of the dataset at ``root``."""
    info_path = Path(root) / "meta" / "info.json"
    if not info_path.is_file():
        raise FileNotFoundError(f"{root}: not a local LeRobot dataset ({info_path} does not exist)")
    return json.loads(info_path.read_text())


def _write(root: str | Path, source: Path, features: dict, cameras: dict[str, CameraCalibration]):
    """Write ``cameras`` (read from ``source``) to calibration.json; returns them."""
    own = [n for n in cameras if "camera.intrinsics" in (features[IMAGE_KEY_PREFIX + n].get("info") or {})]
    if own:
        raise ValueError(f"{source}: camera(s) {own} already carry calibration in {Path(root) / 'meta' / 'info.json'} "
                         "(camera.intrinsics in their feature's info), which is used instead of "
                         "calibration.json: leave them out")  # fmt: skip
    data = {"format": CALIBRATION_FORMAT,
            "cameras": {n: camera_info(c.K, c.c2w, c.mount, c.depth, c.episodes) for n, c in cameras.items()}}  # fmt: skip
    gensplat_folder(root)
    atomic_write_json(calibration_path(root), data)
    return cameras


def _given_intrinsics(names, sizes: dict[str, tuple[int, int]], path, fov: float | None,
                      focal: float | None) -> dict[str, dict]:
    """{camera: {"K": 3x3} or {"fx", "fy", "cx", "cy"}} of ``path``, ``fov`` or ``focal``."""
    if sum(v is not None for v in (path, fov, focal)) != 1:
        raise ValueError("give the cameras' intrinsics with one of --intrinsics FILE, --fov or --focal")
    if path is None:
        if fov is not None and not 0 < fov < 180:
            raise ValueError(f"--fov: a field of view in degrees between 0 and 180, got {fov:g}")
        out = {}
        for n in names:
            w, h = sizes[n]
            f = focal if focal is not None else focal_from_fov(fov, w)
            out[n] = {"fx": f, "fy": f, "cx": w / 2, "cy": h / 2}
        return out
    entries, convention = _parsed(Path(path), "auto")
    missing = [n for n in names if not isinstance(entries.get(n), dict)]
    if missing:
        raise ValueError(f"{path}: no intrinsics of camera(s) {missing} (its cameras: {sorted(entries)})")
    for n in names:
        _no_distortion(f"{path}: camera {n!r}", entries[n])
    return {n: {"K": _intrinsics(f"{path}: camera {n!r}", entries[n], sizes[n],
                                 0.5 if convention == "opencv-w2c" else 0.0).tolist()} for n in names}  # fmt: skip


def _feature_poses(root: Path, keys: list[str]) -> dict[str, dict[int, np.ndarray]]:
    """Per feature key, each episode's (6,) value at its first frame, from the dataset's
    ``data/**/*.parquet``; raises when a value changes within an episode."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    files = sorted((root / "data").rglob("*.parquet"))
    if not files:
        raise FileNotFoundError(f"{root}: no data files (data/**/*.parquet)")
    first, low, high = ({k: {} for k in keys} for _ in range(3))  # key -> episode -> (frame, value) / bounds
    for file in files:
        table = pq.read_table(file, columns=["episode_index", "frame_index", *keys])
        episode, frame = (table[c].to_numpy() for c in ("episode_index", "frame_index"))
        order = np.lexsort((frame, episode))  # by episode, then frame
        episodes, starts = np.unique(episode[order], return_index=True)
        for k in keys:
            column = table[k].combine_chunks()
            sizes = pc.fill_null(pc.list_value_length(column), 0).to_numpy()
            if (sizes != 6).any():
                i = int(np.flatnonzero(sizes != 6)[0])
                raise ValueError(f"{file}: {k} holds {sizes[i]} values at episode {episode[i]}, frame {frame[i]}; "
                                 "a pose is 6: x, y, z, roll, pitch, yaw")  # fmt: skip
            values = column.flatten().to_numpy().astype(np.float64).reshape(-1, 6)
            if not np.isfinite(values).all():
                i = int(np.flatnonzero(~np.isfinite(values).all(axis=1))[0])
                raise ValueError(f"{file}: {k} is not a finite pose at episode {episode[i]}, frame {frame[i]} "
                                 f"({values[i].tolist()}): repair the dataset or leave the camera out with --cameras")  # fmt: skip
            values = values[order]
            lows, highs = np.minimum.reduceat(values, starts), np.maximum.reduceat(values, starts)
            for e, start, lo, hi in zip(episodes.tolist(), starts, lows, highs):
                if e not in first[k] or frame[order[start]] < first[k][e][0]:
                    first[k][e] = (frame[order[start]], values[start])
                low[k][e], high[k][e] = np.minimum(low[k].get(e, lo), lo), np.maximum(high[k].get(e, hi), hi)
    for k in keys:
        for e in first[k]:
            spread = float((high[k][e] - low[k][e]).max())
            if spread > POSE_TOLERANCE:
                raise ValueError(f"{root}: {k} changes within episode {e} by up to {spread:.3g} (more than "
                                 f"{POSE_TOLERANCE:g}): a camera that moves during an episode cannot be "
                                 "reconstructed; leave it out with --cameras")  # fmt: skip
    return {k: {e: v for e, (_, v) in sorted(first[k].items())} for k in keys}


def load_calibration(features: dict, root: str | Path | None = None,
                     episodes: int | None = None) -> dict[str, CameraCalibration]:
    """Calibrated cameras (name -> calibration, in feature order) from LeRobot ``meta.features``;
    a camera whose feature has no calibration takes it from :func:`calibration_path` of ``root``
    when given (its per-episode poses checked against ``episodes``, the dataset's episode count,
    when given)."""
    saved = saved_calibration(root, image_sizes(features), episodes) if root is not None else {}
    out = {}
    for key, ft in features.items():
        if not key.startswith(IMAGE_KEY_PREFIX):
            continue
        name = key[len(IMAGE_KEY_PREFIX) :]
        info = ft.get("info") or {}
        if "camera.intrinsics" not in info:
            if name in saved:
                out[name] = saved[name]
            continue
        ext, sensor = info.get("camera.extrinsics"), info.get("camera.depth")
        out[name] = CameraCalibration(
            name=name,
            K=torch.tensor(info["camera.intrinsics"], dtype=torch.float64),
            c2w=None if ext is None else torch.tensor(ext, dtype=torch.float64),
            mount=info.get("camera.mount", "external"),
            depth=None if sensor is None else DepthSensor(
                torch.tensor(sensor["intrinsics"], dtype=torch.float64), int(sensor["width"]), int(sensor["height"]),
                torch.tensor(sensor["to_camera"], dtype=torch.float64)),
            episodes={int(e): torch.tensor(m, dtype=torch.float64) for e, m in info.get("camera.episodes", {}).items()},
        )  # fmt: skip
    return out


def saved_calibration(root: str | Path, sizes: dict[str, tuple[int, int]],
                      episodes: int | None = None) -> dict[str, CameraCalibration]:
    """The cameras of :func:`calibration_path` among ``sizes`` (name -> (width, height)), checked
    as ``gensplat calibrate`` checks its input, per-episode poses against ``episodes`` (the
    dataset's episode count) when given (empty when the file is absent). Raises ``ValueError``
    naming the file, camera and field, and the fix."""
    path = calibration_path(root)
    if not path.is_file():
        return {}
    fix = f"write it again with `gensplat calibrate from-file --root {root} FILE`"
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, RecursionError) as e:  # not JSON, not UTF-8
        raise ValueError(f"{path}: not valid JSON ({e}); {fix}") from None
    if not isinstance(data, dict) or data.get("format") != CALIBRATION_FORMAT:
        raise ValueError(f"{path}: not a GenSplat calibration file; {fix}")
    try:
        return stored_cameras(path, data.get("cameras"), sizes, episodes)
    except ValueError as e:
        raise ValueError(f"{e}; {fix}") from None


def read_calibration(source: str | Path, sizes: dict[str, tuple[int, int]], convention: str = "auto",
                     episodes: int | None = None) -> dict[str, CameraCalibration]:
    """Validated cameras of ``source``; ``sizes`` maps the dataset's camera names to their
    (width, height) (K is rescaled to it where the file gives another size), ``episodes`` is
    the dataset's episode count (None: per-episode poses not checked against it)."""
    source = Path(source)
    entries, convention = _parsed(source, convention)
    return _cameras(source, entries, sizes, convention, episodes)


def _parsed(source: Path, convention: str) -> tuple[dict, str]:
    """The entries (camera -> fields) of the calibration file ``source`` and its convention."""
    if source.is_dir():
        raise ValueError(f"calibration file {source} is a folder, not a file: give the JSON or YAML file in it")
    if not source.is_file():
        raise FileNotFoundError(f"calibration file {source} does not exist")
    data = _load(source)
    if convention not in CONVENTIONS:
        raise ValueError(f"unknown convention {convention!r}; one of {CONVENTIONS}")
    if not isinstance(data, dict) or not data:
        raise ValueError(f"{source}: expected a mapping of camera names (or a nerfstudio transforms.json)")
    if convention == "auto":
        convention = _detect(data)
    return _nerfstudio_entries(source, data) if convention == "nerfstudio" else data, convention


def stored_cameras(path: Path, cameras, sizes: dict[str, tuple[int, int]],
                   episodes: int | None = None) -> dict[str, CameraCalibration]:
    """Validated cameras of calibration.json's ``cameras`` (name -> ``info``) that are in
    ``sizes``, by the checks of an input file in the gensplat convention."""
    if not isinstance(cameras, dict):
        raise ValueError(f"{path}: field cameras: expected a mapping of camera names, got {cameras!r:.80}")  # noqa: TRY004
    entries = {n: _from_info(info) for n, info in cameras.items() if n in sizes}
    return _cameras(path, entries, sizes, "gensplat", episodes)


def _from_info(info):
    """calibration.json's ``info`` of a camera with the gensplat convention's field names."""
    if not isinstance(info, dict):
        return info
    entry = {_STORED.get(k, k): v for k, v in info.items()}
    if isinstance(entry.get("depth"), dict):
        entry["depth"] = {"K" if k == "intrinsics" else k: v for k, v in entry["depth"].items()}
    if isinstance(entry.get("episodes"), dict):
        entry["episodes"] = {e: {"c2w": c2w} for e, c2w in entry["episodes"].items()}
    return entry


def _cameras(source: Path, entries: dict, sizes: dict[str, tuple[int, int]], convention: str,
             episodes: int | None = None):
    """Validated cameras of ``entries`` (name -> parsed entry of ``convention``), per-episode
    poses checked against ``episodes`` (the dataset's episode count) when given."""
    out = {}
    for name, entry in entries.items():
        where = f"{source}: camera {name!r}"
        if name not in sizes:
            raise ValueError(f"{where} is not an image feature of the dataset (its cameras: {sorted(sizes)})")
        if not isinstance(entry, dict):  # a malformed file: a ValueError like any other
            raise ValueError(f"{where}: expected a mapping of fields, not {type(entry).__name__}")  # noqa: TRY004
        out[name] = _camera(where, name, entry, convention, sizes[name], episodes)
    return out


def _detect(data: dict) -> str:
    """The convention of a parsed file: nerfstudio with ``frames``, opencv-w2c with R or rvec
    (a camera's or an episode's)."""
    if "frames" in data:
        return "nerfstudio"
    entries = [v for v in data.values() if isinstance(v, dict)]
    poses = [*entries, *(p for v in entries if isinstance(v.get("episodes"), dict) for p in v["episodes"].values())]
    return "opencv-w2c" if any(isinstance(p, dict) and ("R" in p or "rvec" in p) for p in poses) else "gensplat"


class _RepeatedKey(ValueError):
    """A mapping of a calibration file gives one key twice (a parser would keep the last silently)."""


def _unique_pairs(pairs: list[tuple]) -> dict:
    """A JSON object's pairs as a dict, or :class:`_RepeatedKey` naming a key given twice."""
    out = {}
    for key, value in pairs:
        if key in out:
            raise _RepeatedKey(f"key {key!r} appears twice in one mapping: keep one")
        out[key] = value
    return out


def _yaml_loader():
    """PyYAML's safe loader, refusing a key given twice in one mapping (:class:`_RepeatedKey`)."""
    import yaml

    class Loader(yaml.SafeLoader):
        def construct_mapping(self, node, deep=False):
            seen = set()
            for key_node, _ in node.value:
                key = self.construct_object(key_node, deep=deep)
                if not isinstance(key, Hashable):  # a list as a key: PyYAML's own error names it
                    break
                if key in seen:
                    raise _RepeatedKey(f"key {key!r} appears twice in one mapping (line {key_node.start_mark.line + 1}): "
                                       "keep one")  # fmt: skip
                seen.add(key)
            return super().construct_mapping(node, deep)

    return Loader


def _load(path: Path):
    """The parsed file: at most MAX_FILE_BYTES of UTF-8 JSON, or YAML without aliases; a key
    given twice in one mapping is refused."""
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ValueError(f"{path}: {size} bytes; a calibration file is at most {MAX_FILE_BYTES} bytes")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text ({e}); save it as UTF-8") from None
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:  # aliases and deep nesting are refused as they are parsed, before anything is built
            depth = 0
            for event in yaml.parse(text, Loader=yaml.SafeLoader):
                depth += isinstance(event, yaml.CollectionStartEvent) - isinstance(event, yaml.CollectionEndEvent)
                if isinstance(event, yaml.AliasEvent):  # nested aliases expand exponentially
                    problem = "YAML aliases (*name) are not allowed in a calibration file; write the values out"
                elif depth > MAX_YAML_DEPTH:
                    problem = (f"nested deeper than {MAX_YAML_DEPTH} levels at line {event.start_mark.line + 1}; "
                               "a calibration file has at most 6")  # fmt: skip
                else:
                    continue
                raise ValueError(f"{path}: {problem}")
            return yaml.load(text, Loader=_yaml_loader())  # a SafeLoader that refuses repeated keys
        except _RepeatedKey as e:
            raise ValueError(f"{path}: {e}") from None
        except (yaml.YAMLError, RecursionError) as e:  # PyYAML's message spans lines: one line here
            raise ValueError(f"{path}: not valid YAML ({' '.join(str(e).split())})") from None
    try:
        return json.loads(text, object_pairs_hook=_unique_pairs)
    except _RepeatedKey as e:
        raise ValueError(f"{path}: {e}") from None
    except (ValueError, RecursionError) as e:  # invalid JSON, an integer of over 4300 digits, deep nesting
        raise ValueError(f"{path}: not valid JSON ({e}); YAML files must end in .yaml or .yml") from None


def _nerfstudio_entries(source: Path, data: dict) -> dict[str, dict]:
    """One ``gensplat``-like entry per frame, named by its file: c2w still in OpenGL axes."""
    top = {k: v for k, v in data.items() if k != "frames"}
    frames = data.get("frames")
    if not isinstance(frames, list) or not frames:
        raise ValueError(f"{source}: field frames: a nerfstudio file needs a non-empty list of frames, "
                         f"got {frames!r:.80}")  # fmt: skip
    entries = {}
    for i, frame in enumerate(frames):
        if not (isinstance(frame, dict) and isinstance(frame.get("file_path"), str) and "transform_matrix"
                in frame and isinstance(frame.get("intrinsics", {}), dict)):  # fmt: skip
            raise ValueError(f"{source}: frames[{i}] must be a mapping with file_path (a string), "
                             "transform_matrix and optionally intrinsics (a mapping)")  # fmt: skip
        name = Path(frame["file_path"]).stem
        if name in entries:
            raise ValueError(f"{source}: camera {name!r} (from file_path) appears in several frames")
        merged = {**top, **frame.get("intrinsics", {}), **frame}
        entries[name] = {"fx": merged.get("fl_x"), "fy": merged.get("fl_y", merged.get("fl_x")),
                         "cx": merged.get("cx"), "cy": merged.get("cy"), "width": merged.get("w"),
                         "height": merged.get("h"), "c2w": frame["transform_matrix"],
                         **{k: merged[k] for k in _DISTORTION if k in merged}}  # fmt: skip
    return entries


def _camera(where: str, name: str, entry: dict, convention: str, size: tuple[int, int],
            episodes: int | None = None) -> CameraCalibration:
    """One validated camera of a parsed entry (see the module docstring)."""
    _no_distortion(where, entry)
    unknown = sorted(set(entry) - _FIELDS.get(convention, set(entry)) - set(_DISTORTION))
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {unknown} for convention {convention} "
                         f"(expected {sorted(_FIELDS[convention])})")  # fmt: skip
    mount = entry.get("mount", "external")
    if mount not in ("external", "wrist"):
        raise ValueError(f"{where}: field 'mount' must be 'external' or 'wrist', got {mount!r}")
    K = _intrinsics(where, entry, size, shift=0.5 if convention == "opencv-w2c" else 0.0)
    _posed(where, "K", K, torch.eye(4, dtype=torch.float64), size)
    c2w, field = _pose(where, entry, convention)
    if c2w is not None:
        _posed(where, field, K, c2w, size)
    poses = {} if entry.get("episodes") is None else _episode_poses(where, entry["episodes"], convention, K, size, episodes)
    if poses and mount != "external":
        raise ValueError(f"{where}: per-episode poses (field episodes) are for external cameras, not {mount} ones")
    if c2w is None and not poses and mount == "external":
        raise ValueError(f"{where}: an external camera needs its pose ({field})")
    missing = [] if c2w is not None or episodes is None else [e for e in range(episodes) if e not in poses]
    if missing:
        raise ValueError(f"{where}: episode(s) {_listed(missing)} of the dataset's {episodes} have no pose: give each "
                         f"its pose in field episodes, or a default pose ({field}) for those not listed")  # fmt: skip
    depth = None if entry.get("depth") is None else _sensor(f"{where}, field depth", entry["depth"], convention)
    return CameraCalibration(name, K, c2w, mount, depth, poses)


def _no_distortion(where: str, entry: dict) -> None:
    distortion = {k: entry[k] for k in _DISTORTION if k in entry}
    if any(_matrix(where, k, v, None).abs().sum() > 0 for k, v in distortion.items()):
        raise ValueError(f"{where}: non-zero distortion {distortion}: undistort the images (e.g. cv2.undistort) "
                         "and give the new camera matrix")  # fmt: skip


def _pose(where: str, entry: dict, convention: str) -> tuple[torch.Tensor | None, str]:
    """(4, 4) OpenCV camera-to-world of an entry (None: none given) and the field(s) naming it."""
    if convention == "opencv-w2c":
        return _w2c_to_c2w(where, entry), "R, t"
    field = "c2w" if convention == "gensplat" else "transform_matrix"  # nerfstudio's, as "c2w" in its entry
    if entry.get("c2w") is None:
        return None, field
    c2w = _matrix(where, field, entry["c2w"], (4, 4))
    return (opengl_to_opencv(c2w) if convention == "nerfstudio" else c2w), field


def _posed(where: str, field: str, K: torch.Tensor, c2w: torch.Tensor, size: tuple[int, int]) -> None:
    """Raise naming ``field`` unless K and c2w make a camera (c2w rigid)."""
    try:
        Cameras(K[None], c2w[None], *size)
    except ValueError as e:
        raise ValueError(f"{where}, field {field}: {e}") from None


def _episode_poses(where: str, value, convention: str, K: torch.Tensor, size: tuple[int, int],
                   episodes: int | None) -> dict[int, torch.Tensor]:
    """{episode index: (4, 4) c2w} of an ``episodes`` field, indices below ``episodes`` when given."""
    if not isinstance(value, dict) or not value:
        raise ValueError(f"{where}, field episodes: expected a mapping of episode indices to poses, got {value!r:.80}")
    fields, given = _POSE_FIELDS[convention], {}
    for key, pose in value.items():
        digits = isinstance(key, str) and key.isascii() and key.isdigit()
        if not (digits or (isinstance(key, int) and not isinstance(key, bool) and key >= 0)):
            raise ValueError(f"{where}, field episodes: {key!r} is not an episode index (a whole number >= 0)")
        index, at = int(key), f"{where}, episode {key}"
        if episodes is not None and index >= episodes:
            raise ValueError(f"{at}: the dataset has no episode {index} (its episodes: 0..{episodes - 1})")
        if index in given:
            raise ValueError(f"{where}, field episodes: episode {index} is given twice")
        if not isinstance(pose, dict) or not set(pose) <= fields:
            raise ValueError(f"{at}: expected a mapping with {' or '.join(sorted(fields))}, got {pose!r:.80}")
        given[index] = at, pose
    if convention == "gensplat":  # checked all at once (DROID: 10^5 episodes); one by one below to name an error's
        try:
            c2w = torch.tensor([pose["c2w"] for _, pose in given.values()], dtype=torch.float64)
            Cameras(K.expand(len(c2w), 3, 3), c2w, *size)
            return {index: m.clone() for index, m in zip(given, c2w)}  # not views: each pickles alone
        except (KeyError, TypeError, ValueError, RuntimeError, OverflowError):
            pass
    poses = {}
    for index, (at, pose) in given.items():
        c2w, field = _pose(at, pose, convention)
        if c2w is None:
            raise ValueError(f"{at}: needs its pose ({field})")
        _posed(at, field, K, c2w, size)
        poses[index] = c2w
    return poses


def _listed(items: list) -> str:
    """``items`` for a message: at most 10, then how many more."""
    return str(items[:10])[:-1] + (f", ... ({len(items) - 10} more)]" if len(items) > 10 else "]")


def _sensor(where: str, entry, convention: str) -> DepthSensor:
    """A validated depth sensor block (see the module docstring)."""
    if not isinstance(entry, dict):
        raise ValueError(f"{where}: expected a mapping with K (or fx, fy, cx, cy), width, height, to_camera")  # noqa: TRY004
    unknown = sorted(set(entry) - _SENSOR_FIELDS)
    if unknown or "to_camera" not in entry or "width" not in entry or "height" not in entry:
        raise ValueError(f"{where}: needs K (or fx, fy, cx, cy), width, height and to_camera (the depth "
                         f"maps' size and the sensor-to-camera transform){f'; unknown {unknown}' if unknown else ''}")  # fmt: skip
    size = _size(where, entry)
    K = _intrinsics(where, entry, size, shift=0.5 if convention == "opencv-w2c" else 0.0)
    to_camera = _matrix(where, "to_camera", entry["to_camera"], (4, 4))
    try:
        Cameras(K[None], to_camera[None], *size)
    except ValueError as e:
        raise ValueError(f"{where}, field to_camera: {e}") from None
    return DepthSensor(K, *size, to_camera)


def _intrinsics(where: str, entry: dict, size: tuple[int, int], shift: float) -> torch.Tensor:
    """(3, 3) K at the dataset's image ``size`` (pixel centres at +0.5)."""
    if "K" in entry:
        K = _matrix(where, "K", entry["K"], (3, 3))
    else:
        values = [entry.get(k) for k in ("fx", "fy", "cx", "cy")]
        if any(v is None for v in values):
            raise ValueError(f"{where}: needs K (3x3) or all of fx, fy, cx, cy")
        fx, fy, cx, cy = (_number(where, k, v) for k, v in zip(("fx", "fy", "cx", "cy"), values))
        K = torch.tensor([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=torch.float64)
    K[:2, 2] += shift
    width, height = size
    if entry.get("width") is not None or entry.get("height") is not None:
        w, h = _size(where, entry)
        K[0] *= width / w
        K[1] *= height / h
    fov = [math.degrees(2 * math.atan2(n, 2 * float(f))) for n, f in ((width, K[0, 0]), (height, K[1, 1]))]
    if not all(FOV_RANGE[0] <= a <= FOV_RANGE[1] for a in fov):
        raise ValueError(f"{where}, field K: focal lengths must be > 0 and give a field of view of "
                         f"{FOV_RANGE[0]:g} to {FOV_RANGE[1]:g} degrees: fx, fy = {float(K[0, 0]):g}, "
                         f"{float(K[1, 1]):g} px give {fov[0]:.3g} x {fov[1]:.3g} degrees at {width}x{height}"
                         " (focal lengths are in pixels; give width and height when the calibration is for "
                         "another image size)")  # fmt: skip
    if not (0 <= K[0, 2] <= width and 0 <= K[1, 2] <= height):
        raise ValueError(f"{where}, field K: principal point ({float(K[0, 2]):.1f}, {float(K[1, 2]):.1f}) lies "
                         f"outside the dataset's {width}x{height} image; give width and height when the "
                         "calibration is for another image size")  # fmt: skip
    return K


def _w2c_to_c2w(where: str, entry: dict) -> torch.Tensor | None:
    """Camera-to-world from OpenCV's world-to-camera ``R`` (or ``rvec``) and ``t``."""
    if "t" not in entry and "R" not in entry and "rvec" not in entry:
        return None
    if "t" not in entry or ("R" in entry) == ("rvec" in entry):
        raise ValueError(f"{where}: opencv-w2c needs t and one of R (3x3) or rvec (3, Rodrigues)")
    if "R" in entry:
        R = _matrix(where, "R", entry["R"], (3, 3))
    else:
        R = axis_angle_to_rotation_matrix(_matrix(where, "rvec", entry["rvec"], (3,))[None])[0]
    t = _matrix(where, "t", entry["t"], (3,))
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3], c2w[:3, 3] = R.T, -R.T @ t
    return c2w


def _matrix(where: str, field: str, value, shape: tuple[int, ...] | None) -> torch.Tensor:
    """Finite float64 numbers of ``shape`` (any shape for None); raises naming ``field``."""
    try:
        m = torch.tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError, OverflowError):
        raise ValueError(f"{where}, field {field}: expected numbers of shape {shape}, "
                         f"got {value!r:.80}") from None  # fmt: skip
    if shape is not None and m.numel() == math.prod(shape) and m.shape != shape:
        m = m.reshape(shape)  # e.g. a (3, 1) tvec or a flat 9-vector
    if shape is not None and m.shape != shape:
        raise ValueError(f"{where}, field {field}: expected shape {shape}, got {tuple(m.shape)}")
    if not torch.isfinite(m).all():
        raise ValueError(f"{where}, field {field}: values must be finite, got {m.tolist()}")
    return m


def _number(where: str, field: str, value) -> float:
    try:
        number = math.nan if isinstance(value, bool) or not isinstance(value, (int, float)) else float(value)
    except OverflowError:  # an int beyond float's range
        number = math.inf
    if not math.isfinite(number):
        raise ValueError(f"{where}, field {field}: expected a finite number, got {value!r:.80}")
    return number


def _size(where: str, entry: dict) -> tuple[int, int]:
    """``entry``'s width and height: positive whole numbers."""
    width, height = (_number(where, k, entry.get(k)) for k in ("width", "height"))
    if width != int(width) or height != int(height) or width < 1 or height < 1:
        raise ValueError(f"{where}: width and height (nerfstudio: w, h) must be positive whole numbers, "
                         f"got {width:g}, {height:g}")  # fmt: skip
    return int(width), int(height)
