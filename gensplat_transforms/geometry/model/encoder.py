"""DINOv2-style ViT/14 image encoder with register tokens (Pi3's ``encoder``)."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .config import PATCH_SIZE, ModelConfig
from .layers import Block, run_block


class PatchEmbed(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, PATCH_SIZE, PATCH_SIZE)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) -> (N, H/14 * W/14, dim), row-major patches."""
        return self.proj(x).flatten(2).transpose(1, 2)


class Encoder(nn.Module):
    """ViT: patch embedding + [cls] + learned positions, then registers, blocks and a final norm.

    Token order inside is [cls, registers, patches]; only the normalised patch tokens leave.
    """

    checkpointing = False

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        d = cfg.dim
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + cfg.enc_pos_grid**2, d))
        self.register_tokens = nn.Parameter(torch.zeros(1, cfg.enc_registers, d))
        self.patch_embed = PatchEmbed(d)
        self.blocks = nn.ModuleList(
            Block(d, cfg.enc_heads, cfg.mlp_ratio, layerscale=cfg.enc_layerscale)
            for _ in range(cfg.enc_depth)
        )
        self.norm = nn.LayerNorm(d, eps=1e-6)

    def position_embedding(self, h: int, w: int) -> torch.Tensor:
        """(1, 1 + h*w, dim): the learned grid resized bicubically (antialiased) to h x w patches."""
        grid = self.pos_embed.shape[1] - 1
        m = round(grid**0.5)
        if (h, w) == (m, m):
            return self.pos_embed
        pe = self.pos_embed.float()
        patches = pe[:, 1:].reshape(1, m, m, -1).permute(0, 3, 1, 2)
        patches = F.interpolate(patches, size=(h, w), mode="bicubic", antialias=True)
        patches = patches.permute(0, 2, 3, 1).reshape(1, h * w, -1)
        return torch.cat([pe[:, :1], patches], dim=1).to(self.pos_embed.dtype)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images: (N, 3, H, W) normalised, H and W multiples of 14 -> (N, H/14 * W/14, dim)."""
        n, _, H, W = images.shape
        x = self.patch_embed(images)
        x = torch.cat([self.cls_token.expand(n, -1, -1), x], dim=1)
        x = x + self.position_embedding(H // PATCH_SIZE, W // PATCH_SIZE)
        r = self.register_tokens.shape[1]
        x = torch.cat([x[:, :1], self.register_tokens.expand(n, -1, -1), x[:, 1:]], dim=1)
        for blk in self.blocks:
            x = run_block(blk, x, None, self.checkpointing and self.training)
        return self.norm(x)[:, 1 + r :]
