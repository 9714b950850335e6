"""Shared pytest fixtures."""

from __future__ import annotations

import json
import random
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

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
