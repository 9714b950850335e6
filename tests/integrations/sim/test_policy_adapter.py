"""A LeRobot checkpoint from ``lerobot-train`` (2 steps) drives the perturbed-camera env."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import gensplat_sim  # noqa: F401  (selects the headless GL backend before MuJoCo loads)
import pytest
import torch

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
pytest.importorskip("mujoco", reason="the simulated world needs the 'sim' extra")
os.environ["HF_HUB_OFFLINE"] = "1"

from gensplat_sim.evaluate import EvalConfig, PerturbedCameraEnv, evaluate
from gensplat_sim.policy_adapter import LeRobotPolicy
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.world import WorldConfig

SIZE = 64
REPO = "gensplat/sim_adapter_test"
POLICIES = Path(__file__).resolve().parents[3] / "policies"


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    """Training output of a tiny Diffusion Policy trained for 2 steps on one 64x64 demo."""
    tmp = tmp_path_factory.mktemp("adapter")
    world = WorldConfig(height=SIZE, width=SIZE)
    record(RecordConfig(tmp / "ds", "pick_place", 1, seed=5, use_videos=False, repo_id=REPO, world=world),
           progress=False)  # fmt: skip
    out = tmp / "train"
    cmd = [
        "bash", str(POLICIES / "train.sh"), "diffusion", "baseline", f"--dataset.repo_id={REPO}",
        f"--dataset.root={tmp / 'ds'}", f"--output_dir={out}", "--steps=2", "--batch_size=2",
        "--num_workers=0", "--save_freq=2", "--policy.down_dims=[16,32]",
        "--policy.noise_scheduler_type=DDIM", "--policy.num_inference_steps=2",
    ]  # fmt: skip
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900, check=False)
    assert run.returncode == 0, run.stderr[-3000:]
    return out


def test_checkpoint_runs_an_evaluation_step(checkpoint):
    policy = LeRobotPolicy(checkpoint)  # a training output folder resolves to checkpoints/last
    assert policy.path.name == "pretrained_model" and policy.config.type == "diffusion"
    env = PerturbedCameraEnv(EvalConfig("pick_place", "large", max_steps=1, world=WorldConfig(SIZE, SIZE)))
    try:
        obs, _ = env.reset(options={"episode_index": 0})
        policy.reset()
        action = policy(obs)
        assert action.shape == (5,) and action.dtype == torch.float32 and torch.isfinite(action).all()
        result = evaluate(policy, env, episodes=1, reset=policy.reset)
    finally:
        env.close()
    assert result.steps == [1] and result.successes == [False]
    assert abs(result.perturbations[0]["theta_deg"]) >= 18  # the left camera really moved


def test_inference_overrides_and_bad_paths(checkpoint, tmp_path):
    policy = LeRobotPolicy(checkpoint / "checkpoints" / "last" / "pretrained_model",
                           overrides={"num_inference_steps": 1})  # fmt: skip
    assert policy.policy.config.num_inference_steps == 1
    with pytest.raises(ValueError, match="no field"):
        LeRobotPolicy(checkpoint, overrides={"not_a_field": 1})
    with pytest.raises(FileNotFoundError, match="pretrained_model"):
        LeRobotPolicy(tmp_path)
