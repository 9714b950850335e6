"""gensplat_lerobot.fast_rows: LeRobot 0.6.1's frame queries read only the columns they need,
and the items are the same as LeRobot's own."""

import os

import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
os.environ["HF_HUB_OFFLINE"] = "1"

import datasets.features.image
import lerobot
import torch
from gensplat_lerobot import fast_rows
from lerobot.datasets.dataset_reader import DatasetReader
from lerobot.datasets.lerobot_dataset import LeRobotDataset

REPO = "local/fast_rows"


@pytest.fixture(scope="module")
def root(scene_dataset):
    """2 episodes of 6 frames at 32x32 (shared: read only)."""
    return scene_dataset(REPO, episodes=2, frames=6, size=32)


def items(root, monkeypatch, query, episodes=None):
    """Every item of the dataset, and how many images were decoded to read them."""
    decoded = []
    decode = datasets.features.image.Image.decode_example
    monkeypatch.setattr(datasets.features.image.Image, "decode_example",
                        lambda self, *a, **k: decoded.append(1) or decode(self, *a, **k))  # fmt: skip
    ds = LeRobotDataset(REPO, root=root, delta_timestamps=query, episodes=episodes)
    return [ds[i] for i in range(len(ds))], len(decoded)


@pytest.mark.parametrize("episodes", [None, [1]])
def test_items_are_lerobot_s_own_with_far_fewer_decodes(root, monkeypatch, episodes):
    assert lerobot.__version__ == fast_rows.FIXED_VERSION  # the version the project pins
    query = {"action": [0.0, 0.1, 0.2, 0.3, 0.4], "observation.state": [-0.1, 0.0]}  # padded at the ends
    monkeypatch.setattr(DatasetReader, "_query_hf_dataset", DatasetReader._query_hf_dataset)  # restored after
    DatasetReader._query_hf_dataset = original = fast_rows._ORIGINAL
    ref, ref_decodes = items(root, monkeypatch, query, episodes)
    assert fast_rows.install() and DatasetReader._query_hf_dataset is not original
    new, new_decodes = items(root, monkeypatch, query, episodes)
    assert len(ref) == len(new) == (12 if episodes is None else 6)
    for a, b in zip(ref, new):
        assert a.keys() == b.keys()
        for key in a:
            if isinstance(a[key], torch.Tensor):
                assert a[key].dtype == b[key].dtype and torch.equal(a[key], b[key]), key
            else:
                assert a[key] == b[key], key
    cameras = sum(k.startswith("observation.images.") for k in ref[0])
    assert new_decodes == cameras * len(new)  # only the item's own frame
    assert ref_decodes == cameras * len(ref) * (1 + len(query["action"]) + len(query["observation.state"]))


def test_another_lerobot_version_is_left_as_it_is(monkeypatch):
    monkeypatch.setattr(DatasetReader, "_query_hf_dataset", fast_rows._ORIGINAL)
    monkeypatch.setattr(lerobot, "__version__", "0.7.0")
    assert not fast_rows.install()
    assert DatasetReader._query_hf_dataset is fast_rows._ORIGINAL
