"""Plain functions that tests in several folders share; the shared fixtures are in conftest.py.

Every test imports it as ``helpers``: tests/conftest.py puts ``tests/`` on ``sys.path`` (pytest's
default "prepend" import mode; the test folders have no ``__init__.py``, so each test file's
name is unique in the whole of ``tests/``). Its asserts are rewritten by pytest like a test's
(``pytest.register_assert_rewrite`` in conftest.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import torch

#: The repository's root (this file is ``tests/helpers.py``).
REPO_ROOT = Path(__file__).resolve().parents[1]


def write_image_features(root: Path, names, width: int, height: int) -> dict:
    """Write a dataset's bare ``meta/info.json``: one video feature ``observation.images.<name>``
    of ``height x width`` per name, none of them calibrated; nothing else of the dataset.

    Returns the features written (a dict the test may change and write again).
    """
    features = {f"observation.images.{n}": {"dtype": "video", "shape": [height, width, 3], "names": None}
                for n in names}  # fmt: skip
    (root / "meta").mkdir(parents=True)
    (root / "meta" / "info.json").write_text(json.dumps({"features": features}))
    return features


def strip_calibration(root: Path, names=("left", "right", "front")) -> None:
    """Remove the calibration from a recorded dataset's image features ``observation.images.<name>``
    (their whole ``info``), as LeRobot records a dataset: nothing else is changed."""
    path = root / "meta" / "info.json"
    info = json.loads(path.read_text())
    for n in names:
        info["features"][f"observation.images.{n}"].pop("info")
    path.write_text(json.dumps(info))


def train_diffusion(*overrides: str) -> subprocess.CompletedProcess:
    """``policies/train.sh diffusion gensplat`` (lerobot-train with the one line) with these
    overrides, offline, with this interpreter's environment first on PATH."""
    cmd = ["bash", str(REPO_ROOT / "policies" / "train.sh"), "diffusion", "gensplat", *overrides]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", "HF_HUB_OFFLINE": "1"}
    return subprocess.run(cmd, check=False, capture_output=True, text=True, env=env, timeout=900)


def assert_same_batch(expected: dict, got: dict, atol: float) -> None:
    """Two collated batches hold the same keys, and the same tensors (dtype, shape, values within
    ``atol``) and other values."""
    assert set(got) == set(expected)  # the batch keys are gone, the report keys kept
    for key, value in expected.items():
        if not isinstance(value, torch.Tensor):  # e.g. LeRobot's task strings
            assert got[key] == value, key
            continue
        assert got[key].dtype == value.dtype and got[key].shape == value.shape, key
        torch.testing.assert_close(got[key].double(), value.double(), atol=atol, rtol=0, msg=key)
