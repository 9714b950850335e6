"""Batch rendering (render_in="batch") through LeRobot: a LeRobotDataset's batch side against
its workers, render_in="auto", and lerobot-train rendering batches after collation. Apart from
test_batched.py so that its CPU and CUDA tests run where the LeRobot extra is not installed."""

import json
from dataclasses import replace

import pytest
import torch
from safetensors import safe_open
from torch.utils.data import DataLoader

from gensplat_transforms.transform import GenSplatConfig

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
from gensplat_lerobot import enable_gensplat, save_settings
from gensplat_lerobot.batch_mode import use_render_in
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from test_batched import assert_same_batch
from test_lerobot import REPO, dataset_root, recorded, train_diffusion  # noqa: F401  (test_lerobot's fixtures)


@pytest.fixture
def root(dataset_root):  # noqa: F811
    """A fresh copy of test_lerobot's recorded dataset (2 episodes of 20 frames, 48x48, RGB-D)."""
    return dataset_root


class RunConfig:
    """What :func:`use_render_in` reads of a lerobot-train config."""

    def __init__(self, device: str) -> None:
        self.trainable_config = type("Policy", (), {"device": device})()


def flip(image: torch.Tensor) -> torch.Tensor:
    """A 2D image transform that must see the rendered view, not the source (module level: picklable)."""
    return image.flip(-1)


def test_lerobot_batch_mode_matches_the_worker_with_2d_transforms_after_rendering(root):
    save_settings(root, GenSplatConfig(probability=0.5, level="large", report=True), {"name": "rgbd"})
    datasets = {}
    for mode in ("worker", "batch"):
        ds = LeRobotDataset(REPO, root=root, image_transforms=flip)
        enable_gensplat(ds)
        ds.gensplat.cfg = replace(ds.gensplat.cfg, render_in=mode)
        assert use_render_in(ds, RunConfig("cpu")) == mode
        datasets[mode] = ds
    assert datasets["batch"].gensplat_image_transforms is None  # moved to the batch side
    batches = {}
    for mode, ds in datasets.items():
        torch.manual_seed(3)
        batches[mode] = next(iter(DataLoader(ds, batch_size=6, shuffle=True)))
    got = datasets["batch"].gensplat_batch(batches["batch"])
    expected = batches["worker"]
    applied = expected["gensplat.applied"][:, 0]
    assert applied.any() and not applied.all()
    assert_same_batch(expected, got, atol=1e-5)


def test_render_in_auto_renders_in_the_workers_without_cuda(root):
    save_settings(root, GenSplatConfig(), {"name": "rgbd"})
    ds = enable_gensplat(LeRobotDataset(REPO, root=root))
    expected = "batch" if torch.cuda.is_available() else "worker"
    assert use_render_in(ds, RunConfig("cuda")) == expected == ds.gensplat.cfg.render_in
    cpu = enable_gensplat(LeRobotDataset(REPO, root=root))
    assert use_render_in(cpu, RunConfig("cpu")) == "worker" and not hasattr(cpu, "gensplat_batch")


def test_lerobot_train_diffusion_policy_renders_batches_after_collation(root, tmp_path):
    """Three lerobot-train steps with the one line, batch mode forced on the CPU, one spawn worker."""
    save_settings(root, GenSplatConfig(probability=1.0, render_in="batch"), {"name": "rgbd"})
    out = tmp_path / "out"
    run = train_diffusion(f"--dataset.repo_id={REPO}", f"--dataset.root={root}", f"--output_dir={out}",
                          "--steps=3", "--batch_size=2", "--num_workers=1", "--save_freq=3", "--log_freq=1")  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    assert "GenSplat rendered its first batch on cpu: 2 of 2 samples augmented" in run.stderr + run.stdout
    assert list((root / "gensplat" / "cache").rglob("episode_*.safetensors"))  # built by the worker
    model = next(out.rglob("pretrained_model"))
    with safe_open(str(model / "model.safetensors"), framework="pt") as f:
        assert f.keys() and not [k for k in f.keys() if "gensplat" in k]  # noqa: SIM118
    for path in [*model.glob("*.json"), next(out.rglob("train_config.json"))]:  # the repo id says gensplat_scene
        text = path.read_text()
        assert not [s for s in ("gensplat.", "gensplat_lerobot", "render_in", "discover_packages") if s in text]
    assert json.loads((model / "config.json").read_text())["type"] == "diffusion"
