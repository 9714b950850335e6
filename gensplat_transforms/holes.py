"""Filling the pixels a render leaves uncovered (disocclusions, parts of the new view that no
source camera saw) with a smooth continuation of the colours around them."""

from __future__ import annotations

import torch
import torch.nn.functional as F

_EPS = 1e-6


def fill_holes(
    color: torch.Tensor,
    alpha: torch.Tensor,
    empty: tuple[float, float, float] | torch.Tensor = (0.0, 0.0, 0.0),
) -> torch.Tensor:
    """Composite a render over a pull-push inpainting of itself.

    The render, taken over a black background, is averaged down a 2x image pyramid (colour
    and alpha alike, so colour / alpha is the coverage-weighted mean colour at each level)
    down to one pixel, then composited back up: each level is drawn "over" the bilinearly
    upsampled level below it. Covered pixels keep their colour, partly covered edges blend
    with their neighbours instead of with black, holes take the colours that surround them.

    Args:
        color: (B, 3, H, W) colour rendered over a black background (premultiplied).
        alpha: (B, 1, H, W) accumulated opacity in [0, 1].
        empty: RGB for an image with no covered pixel at all.
    Returns:
        (B, 3, H, W) float32 (float64 for float64 input): ``color + (1 - alpha) * fill``.
    """
    if color.ndim != 4 or color.shape[1] != 3:
        raise ValueError(f"fill_holes: color must be (B, 3, H, W), got {tuple(color.shape)}")
    if alpha.shape != (color.shape[0], 1, *color.shape[2:]):
        raise ValueError(
            f"fill_holes: alpha must be {(color.shape[0], 1, *color.shape[2:])}, got {tuple(alpha.shape)}"
        )
    dtype = torch.float64 if color.dtype == torch.float64 else torch.float32
    c = torch.nan_to_num(color.to(dtype), nan=0.0, posinf=0.0, neginf=0.0)
    a = torch.nan_to_num(alpha.to(dtype), nan=0.0).clamp(0, 1)
    empty_rgb = torch.as_tensor(empty, dtype=dtype, device=color.device).reshape(1, 3, 1, 1)
    if not torch.isfinite(empty_rgb).all():
        raise ValueError(f"fill_holes: empty must be a finite RGB, got {empty}")
    pyramid = [(c, a)]
    while max(c.shape[-2:]) > 1:
        # ceil_mode averages the partial windows at odd edges over their valid pixels
        c, a = F.avg_pool2d(c, 2, ceil_mode=True), F.avg_pool2d(a, 2, ceil_mode=True)
        pyramid.append((c, a))
    fill = torch.where(a > _EPS, c / a.clamp_min(_EPS), empty_rgb)
    for c, a in reversed(pyramid[:-1]):
        up = F.interpolate(fill, size=c.shape[-2:], mode="bilinear", align_corners=False)
        fill = c + (1 - a) * up
    return fill
