"""Run a trained LeRobot policy checkpoint in the simulated evaluation environment.

:class:`LeRobotPolicy` loads a ``pretrained_model/`` directory written by ``lerobot-train``
(the policy's ``config.json`` and weights, plus its saved pre- and post-processor pipelines:
batching, device, normalisation, unnormalisation), the way ``lerobot-eval`` builds them, and
is the ``policy(obs) -> action`` callable that :func:`~.evaluate.evaluate` expects:

* in: one observation of :class:`~.evaluate.PerturbedCameraEnv` (``observation.images.*``
  (3, H, W) float in [0, 1], ``observation.state`` (12,), ``task`` str), already in LeRobot's
  key and tensor format, so no environment processor is needed;
* out: the (5,) float32 action on the CPU.

Example (a checkpoint written by ``lerobot-train``)::

    policy = LeRobotPolicy("outputs/dp/checkpoints/last/pretrained_model")
    evaluate(policy, PerturbedCameraEnv(EvalConfig(level="large")), 30, reset=policy.reset)
"""

from __future__ import annotations

import os
from pathlib import Path

import torch


class LeRobotPolicy:
    """A LeRobot policy checkpoint as ``policy(obs) -> action``.

    Args:
        pretrained_dir: a checkpoint's ``pretrained_model`` directory (or a training output
            directory, whose ``checkpoints/last/pretrained_model`` is used).
        device: where the policy runs (overrides the device it was trained on).
        overrides: policy-config fields to change for inference, e.g.
            ``{"num_inference_steps": 10}`` for a diffusion policy.
    """

    def __init__(self, pretrained_dir: str | os.PathLike, device: str = "cpu", overrides: dict | None = None):
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies import make_pre_post_processors
        from lerobot.policies.factory import get_policy_class

        path = Path(pretrained_dir)
        if (path / "checkpoints" / "last" / "pretrained_model").is_dir():
            path = path / "checkpoints" / "last" / "pretrained_model"
        if not (path / "config.json").is_file():
            raise FileNotFoundError(f"{path}: not a LeRobot pretrained_model directory (no config.json)")
        self.path = path
        cfg = PreTrainedConfig.from_pretrained(path)
        cfg.device = device
        for key, value in (overrides or {}).items():
            if not hasattr(cfg, key):
                raise ValueError(f"LeRobotPolicy: {type(cfg).__name__} has no field {key!r}")
            setattr(cfg, key, value)
        cfg.pretrained_path = path
        self.config = cfg
        self.policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg).to(device).eval()
        self.preprocessor, self.postprocessor = make_pre_post_processors(
            cfg, pretrained_path=str(path), preprocessor_overrides={"device_processor": {"device": device}}
        )

    def reset(self) -> None:
        """Clear the policy's observation and action queues; call after every env reset."""
        self.policy.reset()
        self.preprocessor.reset()
        self.postprocessor.reset()

    @torch.no_grad()
    def __call__(self, obs: dict) -> torch.Tensor:
        """(5,) action for one environment observation (see the module docstring)."""
        batch = self.preprocessor(dict(obs))
        action = self.postprocessor(self.policy.select_action(batch))
        return action.reshape(-1).float().cpu()
