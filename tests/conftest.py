"""Shared pytest fixtures.

The tests mirror the package: ``tests/<stage>/test_<module>.py`` for the stages of
``gensplat_transforms`` (core, data, calibration, geometry with geometry/model, cache, views,
rendering), ``tests/integrations/<cli|lerobot|sim>``, ``tests/benchmarks`` and ``tests/examples``
for the scripts, and ``tests/`` itself for what crosses the stages (the transform, the public API,
the layers, the walk of an item, training). The folders have no ``__init__.py``: pytest imports
each test file by its name (the default "prepend" import mode), so a test file's name must be
unique in the whole of ``tests/``. Loading this file puts ``tests/`` on ``sys.path``, so every test
imports the helper modules beside it by name (``helpers``, ``tiny_model``, ``tiny_moge``); a
folder's own helpers (``rendering/hard_cases.py``) are imported from that folder's tests only.
"""

from __future__ import annotations

import json
import random
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.register_assert_rewrite("helpers")

from gensplat_transforms.core.cameras import Cameras

#: One real DROID timestep (two calibrated external cameras), kept beside the repository.
DROID_DIR = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "droid_sample"


@dataclass(frozen=True)
class DroidSample:
    """The DROID timestep as stored on disk plus its OpenCV cameras.

    Attributes:
        names: image file names, one per camera.
        c2w_gl: (2, 4, 4) camera-to-world, OpenGL convention, exactly as in transforms.json.
        K: (2, 3, 3) pixel intrinsics.
        width, height: image size (1280 x 720).
        cameras: OpenCV cameras built by hand here (R_cv = R_gl @ diag(1, -1, -1)), so tests
            of ``Cameras.from_opengl`` have an independent reference.
    """

    names: tuple[str, ...]
    c2w_gl: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    cameras: Cameras


@pytest.fixture(autouse=True)
def seeded() -> None:
    """Every test starts from the same state of torch's, NumPy's and Python's global generators:
    the random numbers a test draws without a generator of its own are the same on every run."""
    torch.manual_seed(0)
    np.random.seed(0)
    random.seed(0)


@pytest.fixture(scope="session")
def droid() -> DroidSample:
    path = DROID_DIR / "transforms.json"
    if not path.is_file():
        pytest.skip(f"real DROID sample not found: expected {path} (the shared data folder beside the repo)")
    frames = json.loads(path.read_text())["frames"]
    c2w_gl = torch.tensor([f["transform_matrix"] for f in frames], dtype=torch.float64)
    intr = [f["intrinsics"] for f in frames]
    K = torch.tensor(
        [[[i["fl_x"], 0.0, i["cx"]], [0.0, i["fl_y"], i["cy"]], [0.0, 0.0, 1.0]] for i in intr],
        dtype=torch.float64,
    )
    sizes = {(i["w"], i["h"]) for i in intr}
    assert len(sizes) == 1, f"DROID cameras disagree on image size: {sizes}"
    width, height = sizes.pop()
    c2w_cv = c2w_gl.clone()
    c2w_cv[:, :3, :3] = c2w_gl[:, :3, :3] @ torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    return DroidSample(
        names=tuple(f["file_path"] for f in frames),
        c2w_gl=c2w_gl,
        K=K,
        width=width,
        height=height,
        cameras=Cameras(K, c2w_cv, width, height),
    )


@pytest.fixture(scope="session")
def droid_dir() -> Path:
    if not DROID_DIR.is_dir():
        pytest.skip(f"real DROID sample not found: expected the folder {DROID_DIR}")
    return DROID_DIR


@pytest.fixture(scope="session")
def scene_dataset(tmp_path_factory) -> Callable[..., Path]:
    """The small LeRobot dataset the LeRobot tests read, recorded once per session.

    ``scene_dataset(repo, episodes=, frames=, size=)`` records the procedural tabletop
    (``SceneEpisodes(episodes, frames, size, seed)``, ``gensplat_lerobot.record_scene_dataset``)
    and returns its root: cameras ``left`` and ``right`` (external, calibrated in their
    features' ``info``, depth as sidecars, or LeRobot's depth features with ``depth_as``) and
    ``front``, PNG images of ``size x size``; ``observation.state`` and ``action``. Each set of
    arguments is recorded once and then shared by every test that asks for it: read it, or copy
    it (``dataset_copy``) before changing anything. Skips the test without the LeRobot extra.
    """
    recorded: dict[tuple, Path] = {}

    def record(repo: str = "local/gensplat_scene", *, episodes: int, frames: int, size: int, seed: int = 0,
               depth_as: str = "sidecars") -> Path:  # fmt: skip
        key = (repo, episodes, frames, size, seed, depth_as)
        if key not in recorded:
            pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
            from gensplat_lerobot.scene_dataset import record_scene_dataset

            from gensplat_transforms.cache.builder import SceneEpisodes

            root = tmp_path_factory.mktemp("scene_dataset") / "ds"
            source = SceneEpisodes(num_episodes=episodes, num_frames=frames, size=size, seed=seed)
            record_scene_dataset(root, source, repo, progress=False, depth_as=depth_as)
            recorded[key] = root
        return recorded[key]

    return record


@pytest.fixture
def dataset_copy(tmp_path) -> Callable[..., Path]:
    """``dataset_copy(root, name="ds")``: a copy of the dataset at ``root`` as ``tmp_path / name``,
    for a test that changes it (``scene_dataset``'s recordings are shared)."""

    def copy(root: Path, name: str = "ds") -> Path:
        return Path(shutil.copytree(root, tmp_path / name))

    return copy
