"""The permutation-equivariant decoder: alternating frame-wise and global attention (Pi3's ``decoder``).

No token says which view is which: every frame gets the same register tokens and the same
RoPE positions, and global blocks attend over the union of all frames' tokens. Permuting the
input views therefore permutes every output the same way.
"""

from __future__ import annotations

import torch
from torch import nn

from .config import ModelConfig
from .layers import Block, run_block


def token_positions(h: int, w: int, registers: int, device=None) -> torch.Tensor:
    """(registers + h*w, 2) RoPE (row, column) positions: 0 for registers, 1-based for patches."""
    rows, cols = torch.meshgrid(torch.arange(h, device=device), torch.arange(w, device=device), indexing="ij")
    patches = torch.stack([rows, cols], dim=-1).reshape(-1, 2) + 1
    return torch.cat([patches.new_zeros(registers, 2), patches])


class Decoder(nn.ModuleList):
    """``dec_depth`` RoPE blocks with qk-norm and LayerScale; even ones attend within a frame,
    odd ones across all frames of a sample."""

    checkpointing = False

    def __init__(self, cfg: ModelConfig):
        super().__init__(
            Block(
                cfg.dim,
                cfg.dec_heads,
                cfg.mlp_ratio,
                layerscale=cfg.dec_layerscale,
                qk_norm=True,
                rope_freq=cfg.rope_freq,
            )
            for _ in range(cfg.dec_depth)
        )

    def forward(self, x: torch.Tensor, pos: torch.Tensor, keep: set[int]) -> dict[int, torch.Tensor]:
        """Run all blocks and return the outputs of the blocks in ``keep``.

        Args:
            x: (B, V, T, C) tokens of V frames (registers first).
            pos: (T, 2) positions of one frame's tokens.
            keep: block indices whose outputs are returned.
        Returns:
            {index: (B, V, T, C)}.
        """
        B, V, T, C = x.shape
        frame_pos, global_pos = pos[None], pos.repeat(V, 1)[None]
        out = {}
        for i, blk in enumerate(self):
            if i % 2 == 0:
                x = run_block(blk, x.reshape(B * V, T, C), frame_pos, self.checkpointing and self.training)
            else:
                x = run_block(blk, x.reshape(B, V * T, C), global_pos, self.checkpointing and self.training)
            if i in keep:
                out[i] = x.reshape(B, V, T, C)
        return out
