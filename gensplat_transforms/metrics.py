"""Image-fidelity metrics."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


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


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype, device) -> torch.Tensor:
    """(size,) normalised 1D Gaussian."""
    x = torch.arange(size, dtype=dtype, device=device) - (size - 1) / 2
    g = torch.exp(-(x**2) / (2 * sigma**2))
    return g / g.sum()


def ssim_map(
    pred: torch.Tensor,
    target: torch.Tensor,
    max_val: float = 1.0,
    window: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
) -> torch.Tensor:
    """Per-pixel structural similarity (Wang et al. 2004) of (..., C, H, W) images.

    Local statistics use a ``window`` x ``window`` Gaussian (std ``sigma``) applied without
    padding, so the map is (..., C, H - window + 1, W - window + 1): entry (i, j) belongs
    to the window centred on pixel (i + window // 2, j + window // 2).
    """
    if pred.shape != target.shape or pred.ndim < 3:
        raise ValueError(
            f"ssim: need two (..., C, H, W) images of one shape, got {pred.shape}, {target.shape}"
        )
    if min(pred.shape[-2:]) < window:
        raise ValueError(f"ssim: images of {tuple(pred.shape[-2:])} are smaller than the {window}px window")
    lead, (c, h, w) = pred.shape[:-3], pred.shape[-3:]
    x = pred.double().reshape(-1, c, h, w)
    y = target.double().reshape(-1, c, h, w)
    g = _gaussian_window(window, sigma, x.dtype, x.device)
    gx, gy = g.view(1, 1, 1, -1).expand(c, 1, 1, -1), g.view(1, 1, -1, 1).expand(c, 1, -1, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:
        return F.conv2d(F.conv2d(t, gx, groups=c), gy, groups=c)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = (k1 * max_val) ** 2, (k2 * max_val) ** 2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return s.reshape(*lead, c, *s.shape[-2:])


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    max_val: float = 1.0,
    window: int = 11,
) -> float:
    """Mean SSIM of (..., C, H, W) images (11x11 Gaussian window, std 1.5, K1 = 0.01, K2 = 0.03),
    optionally over the windows centred on pixels where ``mask`` (..., 1, H, W) is true.
    Identical images give 1."""
    s = ssim_map(pred, target, max_val, window)
    if mask is None:
        return float(s.mean())
    r = window // 2
    m = mask[..., r : mask.shape[-2] - r, r : mask.shape[-1] - r].expand_as(s)
    if not m.any():
        raise ValueError("ssim: the mask selects no window centres")
    return float(s[m].mean())
