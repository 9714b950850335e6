"""The calibration and depth format of the simulated datasets, and readers for it.

The simulator writes exactly the library's LeRobot format (:mod:`gensplat_transforms.dataset_format`,
whose writers it uses), so the GenSplat transform reads its datasets like any other:

Cameras
    Images are the features ``observation.images.<name>`` (``video`` or ``image`` storage,
    shape (H, W, 3), names ``["height", "width", "channels"]``, 224x224 by default): the
    external cameras ``left`` and ``right`` and the ``wrist`` camera.

Calibration (``meta/info.json``)
    Each image feature's ``info`` dict carries ``"camera.intrinsics"`` (3x3 nested list, pixels,
    the centre of pixel (row i, column j) at (j + 0.5, i + 0.5)), ``"camera.mount"``
    (``"external"`` or ``"wrist"``) and, for the external cameras, ``"camera.extrinsics"``
    (4x4 nested list, OpenCV camera-to-world: x right, y down, +z viewing direction, metres).
    External cameras are fixed for the whole dataset, so one pose per camera. LeRobot merges
    its own ``video.*`` keys into the same dict and keeps these.

Depth sidecar (external cameras)
    ``<root>/depth/<camera>/episode_{episode_index:06d}.safetensors``: one tensor ``"depth"``
    (T, H, W) float16, metric camera-frame z in metres (0 = invalid), frame t aligned with
    ``frame_index`` t; metadata ``{"camera", "episode_index", "num_frames", "format":
    "gensplat-depth", "format_version": "1"}``; written atomically (temporary file in the same
    folder, then ``os.replace``). MuJoCo renders without multisampling, so colour and depth
    are both sampled at pixel centres.

Simulation sidecar
    ``<root>/sim/``: the state of every frame, for ground truth (see :mod:`.truth`).
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

import torch

from .. import dataset_format as core


def load_depth(root: str | os.PathLike, camera: str, episode_index: int) -> torch.Tensor:
    """One episode's depth of an external camera: (T, 1, H, W) float32 metres, 0 = invalid."""
    return core.load_depth(root, camera, episode_index)


def load_calibration(meta_or_root) -> dict[str, dict[str, Any]]:
    """Calibration of every camera that has one.

    Args:
        meta_or_root: the dataset root folder, its ``LeRobotDatasetMetadata`` or the dataset.
    Returns:
        ``{name: {"feature": key, "mount": str, "height": H, "width": W, "intrinsics": (3, 3)
        float64 tensor, "extrinsics": (4, 4) float64 tensor or None}}`` in feature order.
    """
    if isinstance(meta_or_root, (str, os.PathLike)):
        features = json.loads((Path(meta_or_root) / "meta" / "info.json").read_text())["features"]
    else:
        features = getattr(meta_or_root, "meta", meta_or_root).features
    out = {}
    for name, calib in core.load_calibration(features).items():
        key = core.IMAGE_KEY_PREFIX + name
        shape = dict(
            zip(features[key].get("names") or ["height", "width", "channels"], features[key]["shape"])
        )
        out[name] = {
            "feature": key,
            "mount": calib.mount,
            "height": int(shape["height"]),
            "width": int(shape["width"]),
            "intrinsics": calib.K,
            "extrinsics": calib.c2w,
        }
    return out
