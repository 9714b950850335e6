"""Image-fidelity metrics."""

from __future__ import annotations

import math

import kornia
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


def ssim_map(pred: torch.Tensor, target: torch.Tensor, max_val: float = 1.0, window: int = 11) -> torch.Tensor:
    """Per-pixel structural similarity (Wang et al. 2004; ``kornia.metrics.ssim``) of
    (..., C, H, W) images, computed in float64.

    Local statistics use a ``window`` x ``window`` Gaussian (odd size, std 1.5; K1 = 0.01,
    K2 = 0.03) over valid windows only, so the map is (..., C, H - window + 1, W - window + 1):
    entry (i, j) belongs to the window centred on pixel (i + window // 2, j + window // 2).
    """
    if pred.shape != target.shape or pred.ndim < 3:
        raise ValueError(
            f"ssim: need two (..., C, H, W) images of one shape, got {pred.shape}, {target.shape}"
        )
    if min(pred.shape[-2:]) < window:
        raise ValueError(f"ssim: images of {tuple(pred.shape[-2:])} are smaller than the {window}px window")
    chw = pred.shape[-3:]
    x, y = pred.double().reshape(-1, *chw), target.double().reshape(-1, *chw)
    s = kornia.metrics.ssim(x, y, window, float(max_val), eps=0.0, padding="valid")
    return s.reshape(*pred.shape[:-3], *s.shape[-3:])


def ssim(
    pred: torch.Tensor,
    target: torch.Tensor,
    mask: torch.Tensor | None = None,
    max_val: float = 1.0,
    window: int = 11,
) -> float:
    """Mean SSIM of (..., C, H, W) images (see :func:`ssim_map`),
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


def sharpness_ratio(pred: torch.Tensor, target: torch.Tensor) -> float:
    """Detail of (..., C, H, W) ``pred`` relative to ``target``: the mean absolute difference
    between neighbouring pixels (across rows and columns, channels averaged), pred's over
    target's. 1 when a view is as sharp as the true one, below 1 when blurred, above 1 when
    it has edges the target lacks. PSNR and SSIM favour blur over misplaced detail; this tells
    a blurred view from a sharp one.

    Example:
        >>> image = torch.rand(3, 32, 32)
        >>> blurred = torch.nn.functional.interpolate(image[None, :, ::4, ::4], scale_factor=4.0, mode="bilinear")[0]
        >>> round(sharpness_ratio(image, image), 3), sharpness_ratio(blurred, image) < 0.5
        (1.0, True)
    """

    def detail(x: torch.Tensor) -> float:
        grey = x.double().mean(-3)
        return float(grey.diff(dim=-1).abs().mean() + grey.diff(dim=-2).abs().mean())

    if pred.shape != target.shape:
        raise ValueError(f"sharpness_ratio: need two images of one shape, got {tuple(pred.shape)}, {tuple(target.shape)}")
    reference = detail(target)
    if reference == 0:
        raise ValueError("sharpness_ratio: the target image is flat (no detail to compare with)")
    return detail(pred) / reference
