"""Batch rendering (render_in="batch") through LeRobot: a LeRobotDataset's batch side against
its workers, render_in="auto", and lerobot-train rendering batches after collation. Apart from
rendering/test_batched.py so that its CPU and CUDA tests run where the LeRobot extra is not installed."""

import json
from dataclasses import replace

import pytest
import torch
from safetensors import safe_open
from torch.utils.data import DataLoader

from gensplat_transforms.transform import GenSplatConfig

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
from gensplat_lerobot import enable_gensplat, save_settings
from gensplat_lerobot.batch_mode import attach_batch_renderer, settled_render_in
from gensplat_lerobot.plugin import run_settings
from helpers import assert_same_batch, train_diffusion
from lerobot.datasets.lerobot_dataset import LeRobotDataset

REPO = "local/gensplat_scene"


@pytest.fixture
def root(scene_dataset, dataset_copy):
    """A fresh copy of test_lerobot's recorded dataset (2 episodes of 20 frames, 48x48, RGB-D)."""
    return dataset_copy(scene_dataset(REPO, episodes=2, frames=20, size=48))


class RunConfig:
    """What :func:`settled_render_in` reads of a lerobot-train config."""

    def __init__(self, device: str) -> None:
        self.trainable_config = type("Policy", (), {"device": device})()


def flip(image: torch.Tensor) -> torch.Tensor:
    """A 2D image transform that must see the rendered view, not the source (module level: picklable)."""
    return image.flip(-1)


def test_lerobot_batch_mode_matches_the_worker_with_2d_transforms_after_rendering(root):
    config = GenSplatConfig(probability=0.5, level="large", report=True)
    save_settings(root, config, {"name": "rgbd"})
    datasets = {}
    for mode in ("worker", "batch"):
        ds = LeRobotDataset(REPO, root=root, image_transforms=flip)
        enable_gensplat(ds, replace(config, render_in=mode), {"name": "rgbd"})
        assert attach_batch_renderer(ds) == mode
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
    assert settled_render_in("auto", RunConfig("cuda")) == ("batch" if torch.cuda.is_available() else "worker")
    assert settled_render_in("auto", RunConfig("cpu")) == "worker"
    assert settled_render_in("batch", RunConfig("cpu")) == "batch"  # asked for: kept
    save_settings(root, GenSplatConfig(), {"name": "rgbd"})
    unsettled = enable_gensplat(LeRobotDataset(REPO, root=root))
    with pytest.raises(ValueError, match="render_in 'auto' is not settled"):
        attach_batch_renderer(unsettled)
    base = LeRobotDataset(REPO, root=root)
    cpu = enable_gensplat(base, *run_settings(base, RunConfig("cpu")))  # as the plugin makes it
    assert cpu.gensplat.cfg.render_in == "worker"
    assert attach_batch_renderer(cpu) == "worker" and not hasattr(cpu, "gensplat_batch")


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
