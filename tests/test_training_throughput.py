"""benchmarks/training_throughput.py refuses datasets that would measure the wrong thing."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import training_throughput as tt
from gensplat_lerobot.record import record_scene_dataset

from gensplat_transforms.episodes import SceneEpisodes


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """One episode of 6 frames at 16x16."""
    root = tmp_path_factory.mktemp("throughput") / "ds"
    record_scene_dataset(root, SceneEpisodes(num_episodes=1, num_frames=6, size=16), tt.REPO, progress=False)
    return root


def run_main(monkeypatch, *argv: str) -> str:
    monkeypatch.setattr(sys, "argv", ["training_throughput.py", *argv])
    with pytest.raises(SystemExit) as exit_:
        tt.main()
    return str(exit_.value)


def test_an_epoch_shorter_than_the_workers_is_refused(small, monkeypatch):
    message = run_main(monkeypatch, "--root", str(small), "--size", "16", "--batch-size", "4", "--workers", "2")
    assert "6 frames: 1 batches of 4 per epoch" in message and "Record more episodes" in message


def test_a_recording_of_another_size_is_refused(small, monkeypatch):
    message = run_main(monkeypatch, "--root", str(small), "--size", "32", "--batch-size", "1", "--workers", "0")
    assert "16x16 images, not --size 32" in message
