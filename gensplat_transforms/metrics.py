"""Image-fidelity metrics."""

from __future__ import annotations

import math

import torch


def psnr(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor | None = None, max_val: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of (..., C, H, W) images, optionally over the pixels
    where ``mask`` (..., 1, H, W) is true. Identical images give +inf."""
    err = (pred.double() - target.double()).square()
    if mask is not None:
        m = mask.expand_as(err)
        if not m.any():
            raise ValueError("psnr: the mask selects no pixels")
        err = err[m]
    mse = float(err.mean())
    return float("inf") if mse == 0 else 10 * math.log10(max_val**2 / mse)
