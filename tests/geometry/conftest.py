"""Fixtures of the geometry stage's tests (``tests/geometry`` and ``tests/geometry/model``)."""

from __future__ import annotations

import pytest
import torch

from gensplat_transforms.geometry.model.da3 import DA3Config, DepthAnything3


@pytest.fixture(scope="module")
def small() -> DepthAnything3:
    """DA3-Small (Depth Anything 3) with random weights drawn from seed 0, in eval mode."""
    torch.manual_seed(0)
    model = DepthAnything3(DA3Config("da3-small")).eval()
    with torch.no_grad():  # non-trivial weights (the constructors leave some tensors at zero)
        for p in model.parameters():
            p.normal_(0, 0.05)
    return model
