"""A MoGe-2 of the official form with random weights and a narrow neck, for fast tests
(tests/geometry/model/test_moge.py, tests/geometry/test_monocular.py)."""

from __future__ import annotations

import torch


def _stack(dims: list[int], dim_in: list[int], out: list[int | None] | None) -> dict:
    return {"dim_in": dim_in, "dim_out": out, "dim_res_blocks": dims, "num_res_blocks": [0, 2, 2, 2, 0]
            if out is None else [0, 1, 1, 1, 0], "res_block_in_norm": "none", "res_block_hidden_norm": "none",
            "resamplers": ["conv_transpose"] * 3 + ["bilinear"]}  # fmt: skip


def official_config(backbone: str, dims: list[int], scale: list[int], layers, normal: bool = True) -> dict:
    """A ``model_config`` of the official MoGe-2 form (configs/train/v2.json) with other widths."""
    heads = {"points_head": 3, "mask_head": 1, **({"normal_head": 3} if normal else {})}
    return {
        "encoder": {"backbone": backbone, "intermediate_layers": layers, "dim_out": dims[0]},
        "neck": _stack(dims, [dims[0] + 2, 2, 2, 2, 2], None),
        **{name: _stack(dims, dims, [None] * 4 + [out]) for name, out in heads.items()},
        "scale_head": {"dims": scale},
        "remap_output": "exp",
        "num_tokens_range": [1200, 3600],
    }


#: ViT-S backbone (DINOv2 sizes are fixed by name) with a narrow neck and heads, for fast tests
TINY = official_config("dinov2_vits14", [32, 16, 16, 8, 8], [384, 32, 1], [2, 5, 8, 11])
def randomize(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Non-trivial weights (the constructors leave biases and tokens at zero), a mostly valid mask."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.05 + (1.0 if name.endswith("gamma") else 0.0))
        model.mask_head.output_blocks[-1].bias.fill_(2.0)
    return model
