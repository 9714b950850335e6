"""A MoGe-2 of the official form with random weights and a narrow neck, for fast tests
(tests/geometry/model/test_moge.py, tests/geometry/test_monocular.py)."""

from __future__ import annotations

import torch

from gensplat_transforms.geometry.model.moge import model_config

#: ViT-S backbone (DINOv2 sizes are fixed by name) with a narrow neck and heads, for fast tests
TINY = model_config("dinov2_vits14", [32, 16, 16, 8, 8], [384, 32, 1], [2, 5, 8, 11])


def randomize(model: torch.nn.Module, seed: int = 0) -> torch.nn.Module:
    """Non-trivial weights (the constructors leave biases and tokens at zero), a mostly valid mask."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 0.05 + (1.0 if name.endswith("gamma") else 0.0))
        model.mask_head.output_blocks[-1].bias.fill_(2.0)
    return model
