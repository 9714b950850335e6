"""Pi3's geometry heads: per-frame transformer decoders, pixel-shuffle point / confidence heads and
the camera head (9-D rotation -> SVD orthogonalisation, 3-D translation -> 4x4 camera-to-world)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .config import PATCH_SIZE, ModelConfig
from .layers import Block, run_block


class HeadDecoder(nn.Module):
    """Linear projection, ``head_depth`` RoPE blocks (no qk-norm, no LayerScale) within each frame,
    linear output. Pi3's ``TransformerDecoder``."""

    checkpointing = False

    def __init__(self, in_dim: int, out_dim: int, cfg: ModelConfig):
        super().__init__()
        self.projects = nn.Linear(in_dim, cfg.head_dim)
        self.blocks = nn.ModuleList(
            Block(cfg.head_dim, cfg.head_heads, cfg.mlp_ratio, rope_freq=cfg.rope_freq)
            for _ in range(cfg.head_depth)
        )
        self.linear_out = nn.Linear(cfg.head_dim, out_dim)

    def forward(self, x: torch.Tensor, pos: torch.Tensor) -> torch.Tensor:
        """x: (N, T, in_dim) frame tokens; pos: (T, 2). Returns (N, T, out_dim)."""
        x = self.projects(x)
        for blk in self.blocks:
            x = run_block(blk, x, pos[None], self.checkpointing and self.training)
        return self.linear_out(x)


class PixelHead(nn.Module):
    """Each patch token -> a 14 x 14 block of ``channels`` values (linear + pixel shuffle)."""

    def __init__(self, dim: int, channels: int):
        super().__init__()
        self.proj = nn.Linear(dim, channels * PATCH_SIZE**2)

    def forward(self, tokens: torch.Tensor, h: int, w: int) -> torch.Tensor:
        """tokens: (N, h*w, dim) patch tokens -> (N, 14h, 14w, channels)."""
        n = tokens.shape[0]
        x = self.proj(tokens).transpose(1, 2).reshape(n, -1, h, w)
        return F.pixel_shuffle(x, PATCH_SIZE).permute(0, 2, 3, 1)


class ResConvBlock(nn.Module):
    """Residual stack of three linear + ReLU layers (1x1 convolutions over tokens)."""

    def __init__(self, dim: int):
        super().__init__()
        self.res_conv1 = nn.Linear(dim, dim)
        self.res_conv2 = nn.Linear(dim, dim)
        self.res_conv3 = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + F.relu(self.res_conv3(F.relu(self.res_conv2(F.relu(self.res_conv1(x))))))


def svd_orthogonalize(m: torch.Tensor) -> torch.Tensor:
    """(N, 9) -> (N, 3, 3) rotations: the nearest rotation to the row-normalised 3x3 matrix.

    With M = U S V^T the result is U diag(1, 1, det(U V^T)) V^T (never a reflection).
    """
    m = F.normalize(m.reshape(-1, 3, 3), dim=-1)
    u, _, vh = torch.linalg.svd(m)
    d = torch.det(u @ vh)
    u = torch.cat([u[..., :2], u[..., 2:] * d[:, None, None]], dim=-1)
    return u @ vh


class CameraHead(nn.Module):
    """Frame tokens -> camera-to-world 4x4: two residual blocks, mean over patches, two-layer MLP,
    translation (``fc_t``) and 9-D rotation (``fc_rot``) orthogonalised by SVD."""

    def __init__(self, dim: int):
        super().__init__()
        self.res_conv = nn.ModuleList(ResConvBlock(dim) for _ in range(2))
        self.more_mlps = nn.Sequential(nn.Linear(dim, dim), nn.ReLU(), nn.Linear(dim, dim), nn.ReLU())
        self.fc_t = nn.Linear(dim, 3)
        self.fc_rot = nn.Linear(dim, 9)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        """tokens: (N, h*w, dim) patch tokens -> (N, 4, 4) camera-to-world."""
        for blk in self.res_conv:
            tokens = blk(tokens)
        feat = self.more_mlps(tokens.mean(dim=1))
        pose = torch.eye(4, device=feat.device, dtype=feat.dtype).repeat(feat.shape[0], 1, 1)
        pose[:, :3, :3] = svd_orthogonalize(self.fc_rot(feat))
        pose[:, :3, 3] = self.fc_t(feat)
        return pose
