"""Transformer building blocks shared by the encoder, the decoder and the heads.

Module and parameter names follow DINOv2 / Pi3 so that checkpoints load without renaming:
``norm1, attn.{qkv, q_norm, k_norm, proj}, ls1.gamma, norm2, mlp.{fc1, fc2}, ls2.gamma``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint


def rope_2d(x: torch.Tensor, pos: torch.Tensor, base: float) -> torch.Tensor:
    """Rotary position embedding over two image axes.

    The first half of each head's channels encodes the row, the second half the column;
    within a half, channel i pairs with channel i + D/2 ("rotate half") at frequency
    base^(-2i/D).

    Args:
        x: (B, heads, T, C) queries or keys, C divisible by 4.
        pos: (B or 1, T, 2) integer (row, column) positions.
        base: frequency base (Pi3: 100).
    Returns:
        (B, heads, T, C), same dtype as ``x``.
    """
    d = x.shape[-1] // 2
    inv_freq = base ** (-torch.arange(0, d, 2, device=x.device, dtype=torch.float32) / d)
    out = []
    for axis, part in enumerate(x.chunk(2, dim=-1)):
        angle = pos[..., axis, None].float() * inv_freq  # (B, T, d/2)
        angle = torch.cat([angle, angle], dim=-1)[:, None]  # (B, 1, T, d)
        a, b = part.chunk(2, dim=-1)
        part = part * angle.cos().to(x.dtype) + torch.cat([-b, a], dim=-1) * angle.sin().to(x.dtype)
        out.append(part)
    return torch.cat(out, dim=-1)


class Attention(nn.Module):
    """Multi-head self-attention with optional per-head LayerNorm on q and k and RoPE-2D."""

    def __init__(self, dim: int, heads: int, qk_norm: bool = False, rope_freq: float | None = None):
        super().__init__()
        self.heads, self.rope_freq = heads, rope_freq
        self.qkv = nn.Linear(dim, 3 * dim)
        if qk_norm:
            self.q_norm = nn.LayerNorm(dim // heads)
            self.k_norm = nn.LayerNorm(dim // heads)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        """x: (B, T, dim); pos: (B or 1, T, 2) when RoPE is on. Returns (B, T, dim)."""
        B, T, C = x.shape
        q, k, v = self.qkv(x).reshape(B, T, 3, self.heads, C // self.heads).permute(2, 0, 3, 1, 4)
        if hasattr(self, "q_norm"):
            q, k = self.q_norm(q).to(v.dtype), self.k_norm(k).to(v.dtype)
        if self.rope_freq is not None:
            q, k = rope_2d(q, pos, self.rope_freq), rope_2d(k, pos, self.rope_freq)
        x = F.scaled_dot_product_attention(q, k, v)
        return self.proj(x.transpose(1, 2).reshape(B, T, C))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), float(init)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block: x + ls1(attn(norm1 x)), then x + ls2(mlp(norm2 x)).

    ``layerscale=None`` leaves LayerScale out (no ``ls*`` parameters), as in Pi3's heads.
    """

    def __init__(
        self,
        dim: int,
        heads: int,
        mlp_ratio: float,
        layerscale: float | None = None,
        qk_norm: bool = False,
        rope_freq: float | None = None,
    ):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, heads, qk_norm, rope_freq)
        self.ls1 = LayerScale(dim, layerscale) if layerscale else nn.Identity()
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, int(dim * mlp_ratio))
        self.ls2 = LayerScale(dim, layerscale) if layerscale else nn.Identity()

    def forward(self, x: torch.Tensor, pos: torch.Tensor | None = None) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x), pos))
        return x + self.ls2(self.mlp(self.norm2(x)))


def run_block(block: Block, x: torch.Tensor, pos: torch.Tensor | None, checkpointed: bool) -> torch.Tensor:
    """Apply ``block``, recomputing its activations in the backward pass when ``checkpointed``."""
    if checkpointed and torch.is_grad_enabled():
        return checkpoint(block, x, pos, use_reentrant=False)
    return block(x, pos)
