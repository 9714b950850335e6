"""Teachers for 3D-prior distillation: camera-frame point maps and camera poses of a timestep.

``TrueGeometryTeacher`` reads the dataset's own geometry (simulation, RGB-D: metric depth and
calibration); ``Pi3Teacher`` runs a frozen full-size model initialised from Pi3 weights (its
geometry is up to scale, so the trainer aligns the student's scale before comparing).
"""

from __future__ import annotations

from pathlib import Path
from typing import Protocol

import torch

from ...core.views import Views, valid_depth
from .checkpoints import load_pi3_weights
from .config import ModelConfig
from .gensplat import GenSplatModel


class Teacher(Protocol):
    """Attributes:
    metric: True when the teacher's geometry is in metres (no scale alignment needed).
    """

    metric: bool

    def geometry(self, views: Views) -> tuple[torch.Tensor, torch.Tensor]:
        """(points (V, H, W, 3) camera frame, z <= 0 where unknown; poses (V, 4, 4) camera-to-world)."""
        ...


def camera_points(depth: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Camera-frame points (V, H, W, 3) of depth maps (V, 1, H, W) with intrinsics K (V, 3, 3)
    (pixel centres at +0.5). Invalid depth (see ``valid_depth``) gives the zero point."""
    _, _, H, W = depth.shape
    z = depth[:, 0].float()
    z = torch.where(valid_depth(z), z, torch.zeros_like(z))
    K = K.float()
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    x = (u - K[:, None, None, 0, 2]) / K[:, None, None, 0, 0] * z
    y = (v - K[:, None, None, 1, 2]) / K[:, None, None, 1, 1] * z
    return torch.stack([x, y, z], dim=-1)


class TrueGeometryTeacher:
    """The dataset's metric depth and calibrated camera-to-world poses."""

    metric = True

    def geometry(self, views: Views) -> tuple[torch.Tensor, torch.Tensor]:
        if views.cameras is None or views.depths is None:
            raise ValueError("TrueGeometryTeacher needs views with calibrated cameras and depth")
        return camera_points(views.depths, views.cameras.K), views.cameras.c2w.float()


class Pi3Teacher:
    """A frozen :class:`GenSplatModel` with Pi3 geometry weights (its local points and poses).

    Args:
        weights: Pi3 ``model.safetensors`` (or its directory); must exist.
        config: model size the weights fit (default: full, the official Pi3 checkpoint).
        device: where the teacher runs.
        autocast_dtype: e.g. torch.bfloat16 on a GPU.
    """

    metric = False

    def __init__(self, weights: str | Path, config: ModelConfig | None = None,
                 device: str | torch.device = "cpu", autocast_dtype: torch.dtype | None = None) -> None:  # fmt: skip
        model = GenSplatModel(config or ModelConfig.full())
        self.report = load_pi3_weights(model, weights)  # raises FileNotFoundError without the file
        if self.report.missing_outside_gaussian_head:
            raise ValueError(f"{weights}: not a complete Pi3 geometry checkpoint: {self.report}")
        self.model = model.to(device).eval().requires_grad_(False)
        self.autocast_dtype = autocast_dtype

    @torch.no_grad()
    def geometry(self, views: Views) -> tuple[torch.Tensor, torch.Tensor]:
        device = self.model.image_mean.device
        with torch.autocast(device.type, dtype=self.autocast_dtype, enabled=self.autocast_dtype is not None):
            out = self.model(views.images.to(device, torch.float32)[None])
        return out["local_points"][0].float().cpu(), out["camera_poses"][0].float().cpu()
