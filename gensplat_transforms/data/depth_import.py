"""A camera's recorded depth as the dataset's depth sidecars (``gensplat import-depth``).

Sensor recordings keep depth as one image per frame (16-bit PNG in millimetres, as RealSense,
Azure Kinect and ROS tools write it; 32-bit float TIFF in metres) or as an array per episode
(``.npy``, ``.npz``). :func:`import_depth` reads one camera's, checks it against the dataset
(frames per episode, image size, plausible distances) and writes
``<root>/depth/<camera>/episode_<index:06d>.safetensors`` (:mod:`.data.format`), atomically,
episode by episode: the dataset's own files are not touched.

The depth must be z-depth along the camera's optical axis, registered to the colour image
(the colour camera's intrinsics and size: e.g. ``rs2::align`` to colour for a RealSense), or
the camera's depth sensor's own at the size its calibration's ``depth`` block gives
(:mod:`.calibration`; registered when read); 0, negative and non-finite values mark pixels
without depth.

``source`` names each episode's depth with ``{episode}`` (a format field: ``{episode:06d}``
zero-pads): a folder of frame images, a glob of them (``.../ep{episode}/*.png``), or one
``.npy``/``.npz`` array of shape (T, H, W). Frame files are taken in natural order
(``2.png`` before ``10.png``).
"""

from __future__ import annotations

import glob
import os
import re
import zipfile
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image
from tqdm.auto import tqdm

from .format import depth_path, open_depth, save_depth, storable_depth

#: metres per stored unit, by name (``units`` also takes a number)
UNITS = {"mm": 1e-3, "cm": 1e-2, "m": 1.0}
FRAME_SUFFIXES = (".png", ".tif", ".tiff", ".npy")
EPISODE_SUFFIXES = (".npy", ".npz")
#: median distances outside this range (metres) mean the units were guessed wrong
PLAUSIBLE_M = (0.05, 50.0)


@dataclass(frozen=True)
class ImportedEpisode:
    """What one episode's import wrote (``skipped``: a valid sidecar was there already)."""

    frames: int
    invalid: float  # fraction of pixels without depth
    median_m: float  # median of the valid depths, metres
    skipped: bool = False


def import_depth(root: str | Path, camera: str, source: str, lengths: dict[int, int], size: tuple[int, int],
                 units: str | float | None = None, overwrite: bool = False,
                 progress: bool = True) -> dict[int, ImportedEpisode]:  # fmt: skip
    """Write the depth sidecars of ``camera`` for the episodes of ``lengths``.

    Args:
        root: dataset root.
        source: where each episode's depth is, with ``{episode}`` (module docstring).
        lengths: episode index -> its number of frames in the dataset.
        size: (width, height) of the camera's images.
        units: metres per stored value: "mm", "cm", "m" or a number; default "mm" for
            integer data and "m" for floating-point data, then checked: a median distance
            outside ``PLAUSIBLE_M`` raises, naming the units to give instead.
        overwrite: replace existing sidecars (default: keep those of the right shape).
    Raises:
        ValueError naming the episode and file: frame counts or sizes that differ from the
        dataset's, unreadable or non-depth files (8-bit or colour images), no valid pixel.
        FileNotFoundError: an episode's depth is not where ``source`` says.
    """
    try:
        named = source.format(episode=0) != source.format(episode=1)
    except (KeyError, IndexError, ValueError) as e:
        raise ValueError(f"import_depth: the source {source!r} is not a pattern of {{episode}} ({type(e).__name__}: "
                         f"{e}); e.g. 'raw/ep{{episode:03d}}/*.png'") from None  # fmt: skip
    if not named:
        raise ValueError(f"import_depth: the source {source!r} must name the episode, e.g. 'raw/ep{{episode:03d}}/*.png'")
    scale = _scale(units)
    folder = depth_path(root, camera, 0).parent
    for p in (folder, folder.parent):
        if p.exists() and not p.is_dir():
            raise ValueError(f"{p} is a file where the folder of depth sidecars goes: move it away")
    real, dataset = Path(os.path.realpath(folder)), Path(os.path.realpath(root))
    if real.is_relative_to(dataset) and real != dataset / folder.relative_to(root):
        raise ValueError(f"{folder} leads through a symbolic link to {real}, another of the dataset's folders, "
                         "which import-depth never writes into: remove the link")  # fmt: skip
    done = {}
    for episode, length in tqdm(sorted(lengths.items()), desc=f"depth of {camera}", unit="episode",
                                disable=not progress):  # fmt: skip
        target = depth_path(root, camera, episode)
        if not overwrite and _valid(target, (length, size[1], size[0])):
            done[episode] = ImportedEpisode(length, float("nan"), float("nan"), skipped=True)
            continue
        where = source.format(episode=episode)
        metres, kind = _episode_metres(where, length, size, scale)
        invalid = float((metres <= 0).float().mean())
        if invalid == 1:
            raise ValueError(f"{where}: no pixel of episode {episode} has depth (all 0, negative or non-finite)")
        sample = metres[:, ::4, ::4]  # the median of every 16th pixel
        median = float(sample[sample > 0].float().median()) if (sample > 0).any() else float(metres[metres > 0].median())
        if scale is None and not PLAUSIBLE_M[0] <= median <= PLAUSIBLE_M[1]:
            raise ValueError(f"{where}: median depth {median:.4g} m with the values read as "
                             f"{'m' if kind == 'f' else 'mm'}; give the units (--units mm, cm, m or metres per unit)")  # fmt: skip
        save_depth(root, camera, episode, metres)
        done[episode] = ImportedEpisode(length, invalid, median)
    return done


def _scale(units: str | float | None) -> float | None:
    if units is None:
        return None
    try:
        scale = UNITS[units] if units in UNITS else float(units)
    except (TypeError, ValueError):
        raise ValueError(f"import_depth: units must be one of {sorted(UNITS)} or metres per unit, got {units!r}") from None
    if not np.isfinite(scale) or scale <= 0:
        raise ValueError(f"import_depth: metres per unit must be a positive number, got {units!r}")
    return scale


def _valid(path: Path, shape: tuple[int, int, int]) -> bool:
    """Whether ``path`` is a readable depth sidecar of ``shape`` (T, H, W)."""
    try:
        return path.is_file() and open_depth(path).get_shape() == shape
    except ValueError:
        return False


def _episode_metres(where: str, length: int, size: tuple[int, int], scale: float | None) -> tuple[torch.Tensor, str]:
    """(T, H, W) float16 metres of one episode (0 = no depth), read frame by frame and
    checked against its length and size, and the numpy kind of its values ("u", "i", "f")."""
    path = Path(where)
    if path.suffix in EPISODE_SUFFIXES and not glob.has_magic(where):
        if not path.is_file():
            raise FileNotFoundError(f"{where}: no such depth file")
        array = _read_array(path, (length, size[1], size[0]))
        names, frames = [f"frame {t}" for t in range(len(array))], list(array)
    else:
        frames, others = _frame_files(where)
        names = [str(f) for f in frames]
    if len(frames) != length:
        found = f"{len(frames)} frames" + (f" ({names[0]} .. {names[-1]})" if frames else "")
        if path.suffix not in EPISODE_SUFFIXES and others:
            found += f" of types {', '.join(FRAME_SUFFIXES)} (files of types {others} not read)"
        raise ValueError(f"{where}: {found}; the dataset's episode has {length}")
    width, height = size
    out, kind = torch.empty(length, height, width, dtype=torch.float16), ""
    for t, (name, frame) in enumerate(zip(names, frames)):
        raw = _read_frame(frame, size) if isinstance(frame, Path) else frame
        if raw.shape != (height, width):
            raise ValueError(f"{where}: {name} holds depth of shape {raw.shape}, the camera's images are {width}x"
                             f"{height}: register the depth to the colour camera first (its intrinsics and size, e.g. "
                             "rs2::align to colour for a RealSense)")  # fmt: skip
        kind = kind or raw.dtype.kind
        if scale is None and kind in "ui" and raw.dtype.itemsize == 1:
            raise ValueError(f"{where}: 8-bit values (0-255) are too coarse for millimetres, the units guessed for "
                             "integers; give the units if they are depth (--units cm, or metres per unit)")  # fmt: skip
        if raw.dtype.kind != kind:
            raise ValueError(f"{where}: {name} holds {raw.dtype} values where the frames before hold "
                             f"{'floats' if kind == 'f' else 'integers'}: one episode, one kind of values")  # fmt: skip
        unit = scale if scale is not None else (1.0 if kind == "f" else UNITS["mm"])
        out[t] = storable_depth(torch.from_numpy(raw.astype(np.float32)) * unit)  # before float16: no overflow
    return out, kind


def _frame_files(where: str) -> tuple[list[Path], list[str]]:
    """The frame files of one episode (a folder's or a glob's) in natural order, and the
    suffixes of the other files there (not read)."""
    if glob.has_magic(where):
        files = [Path(p) for p in glob.glob(where)]
    elif Path(where).is_dir():
        files = list(Path(where).iterdir())
    else:
        raise FileNotFoundError(f"{where}: no such folder of depth frames")
    files = [p for p in files if p.is_file()]
    frames = [p for p in files if p.suffix.lower() in FRAME_SUFFIXES]
    others = sorted({p.suffix.lower() or p.name for p in files} - set(FRAME_SUFFIXES))
    return sorted(frames, key=lambda p: [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]), others


def _read_frame(path: Path, size: tuple[int, int]) -> np.ndarray:
    """(H, W) raw values of one depth frame: a 16/32-bit integer or float image, or .npy."""
    if path.suffix.lower() == ".npy":
        frame = _read_array(path, (size[1], size[0]))
    else:
        try:
            with Image.open(path) as image:
                mode = image.mode
                frame = np.array(image)
        except (OSError, ValueError, Image.DecompressionBombError) as e:
            raise ValueError(f"{path}: unreadable image ({e})") from e
        if mode not in ("I;16", "I;16B", "I;16L", "I", "F"):
            raise ValueError(f"{path}: a {mode} image is not depth (depth images are 16-bit or 32-bit, one channel)")
    if frame.ndim != 2:
        raise ValueError(f"{path}: a depth frame must be (H, W), got shape {frame.shape}")
    return frame


def _read_array(path: Path, shape: tuple[int, ...]) -> np.ndarray:
    """A .npy array, or the one array (or ``depth``) of a .npz, as numbers, of ``shape``
    ((T, H, W) or (H, W)): its npy header is checked before any data is read (a small .npz may
    decompress to gigabytes, a header may claim any shape)."""
    want = "(T, H, W)" if len(shape) == 3 else "(H, W)"
    try:
        with _npy_member(path) as f:
            version = np.lib.format.read_magic(f)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            found, _, dtype = read_header(f)
            if dtype.kind not in "uif":
                raise ValueError(f"depth of dtype {dtype}, expected integers or floats (pickled objects are not read)")
            if len(found) != len(shape):
                raise ValueError(f"depth must be {want}, got shape {found}")
            if found != shape:
                raise ValueError(f"depth of shape {found}, expected {shape}: {want} with the dataset's frames and "
                                 "the camera's image size (register the depth to the colour camera first)")  # fmt: skip
            f.seek(0)
            return np.lib.format.read_array(f, allow_pickle=False)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise ValueError(f"{path}: unreadable depth array ({e})") from e


@contextmanager
def _npy_member(path: Path):
    """The open .npy file, or the .npz's one member (or ``depth``)."""
    if path.suffix.lower() != ".npz":
        with open(path, "rb") as f:
            yield f
        return
    with zipfile.ZipFile(path) as z:
        members = {n.removesuffix(".npy"): n for n in z.namelist()}  # NumPy's suffix, or a member without it
        if "depth" not in members and len(members) != 1:
            raise ValueError(f"holds {sorted(members)}; expected one array or one named 'depth'")
        with z.open(members["depth"] if "depth" in members else next(iter(members.values()))) as f:
            yield f
