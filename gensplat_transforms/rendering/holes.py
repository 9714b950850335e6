"""Filling the pixels a render leaves uncovered (disocclusions, parts of the new view that no
source camera saw) with a smooth continuation of the colours around them."""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from ..core.jit import _jit

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

    Float32 CPU images (a dataloader worker's) take a compiled pass, equal to the tensor
    operations within float rounding.
    """
    if color.ndim != 4 or color.shape[1] != 3:
        raise ValueError(f"fill_holes: color must be (B, 3, H, W), got {tuple(color.shape)}")
    if alpha.shape != (color.shape[0], 1, *color.shape[2:]):
        raise ValueError(
            f"fill_holes: alpha must be {(color.shape[0], 1, *color.shape[2:])}, got {tuple(alpha.shape)}"
        )
    dtype = torch.float64 if color.dtype == torch.float64 else torch.float32
    empty_rgb = torch.as_tensor(empty, dtype=dtype).reshape(1, 3, 1, 1)
    if not torch.isfinite(empty_rgb).all():  # checked on the CPU: no wait for the device
        raise ValueError(f"fill_holes: empty must be a finite RGB, got {empty}")
    if not color.numel():  # no image or no pixel: nothing to fill
        return color.to(dtype).clone()
    if dtype == torch.float32 and color.device.type == "cpu" and not (color.requires_grad or alpha.requires_grad):
        out = np.empty(tuple(color.shape), np.float32)
        _pull_push_cpu(color.float().contiguous().numpy(), alpha.float().contiguous().numpy(), empty_rgb.numpy().ravel(),
                       np.float32(_EPS), out)  # fmt: skip
        return torch.from_numpy(out)
    return _pull_push(color.to(dtype), alpha.to(dtype), empty_rgb.to(color.device))


def _pull_push(color: torch.Tensor, alpha: torch.Tensor, empty_rgb: torch.Tensor) -> torch.Tensor:
    """:func:`fill_holes` in tensor operations, for any device and float dtype."""
    # colour and alpha side by side in one (B, 4, H, W) tensor: one pooling per level
    level = torch.empty((color.shape[0], 4, *color.shape[2:]), dtype=color.dtype, device=color.device)
    torch.nan_to_num(color, nan=0.0, posinf=0.0, neginf=0.0, out=level[:, :3])
    torch.nan_to_num(alpha, nan=0.0, out=level[:, 3:]).clamp_(0, 1)
    pyramid = [level]
    while max(level.shape[-2:]) > 1:
        level = _halve(level)
        pyramid.append(level)
    c, a = level[:, :3], level[:, 3:]
    fill = torch.where(a > _EPS, c / a.clamp_min(_EPS), empty_rgb)
    for level in reversed(pyramid[:-1]):
        fill = torch.addcmul(level[:, :3], 1 - level[:, 3:], _upsample(fill, level.shape[-2:]))
    return fill


def _halve(x: torch.Tensor) -> torch.Tensor:
    """``F.avg_pool2d(x, 2, ceil_mode=True)``: windows at odd edges average their valid
    pixels. Large levels of even sizes add the four strided quarters in the pooling's order
    instead: the same values, 2-3x faster on the CPU from 2**15 values on (below that, the
    four operations cost more than the pooling)."""
    if x.shape[-2] % 2 or x.shape[-1] % 2 or x.numel() < 2**15:
        return F.avg_pool2d(x, 2, ceil_mode=True)
    return (((x[..., ::2, ::2] + x[..., ::2, 1::2]) + x[..., 1::2, ::2]) + x[..., 1::2, 1::2]) * 0.25


def _upsample(x: torch.Tensor, size: torch.Size) -> torch.Tensor:
    """Bilinear resize (align_corners=False) of (B, C, h, w) to ``size``, computed as B*C
    one-channel images: on the CPU torch takes its faster channels-last kernel for them
    (equal to within float rounding)."""
    b, c = x.shape[:2]
    one = F.interpolate(x.reshape(b * c, 1, *x.shape[2:]), size=size, mode="bilinear", align_corners=False)
    return one.reshape(b, c, *size)


@_jit()
def _pull_push_cpu(color, alpha, empty, eps, out):
    """:func:`fill_holes` of float32 (B, 3, H, W) ``color`` and (B, 1, H, W) ``alpha`` over
    ``empty`` (3,), compiled, into ``out`` (B, 3, H, W); each level's colour and alpha (4, h*w)."""
    height, width = color.shape[2], color.shape[3]
    sizes = [(height, width)]
    while max(sizes[-1]) > 1:
        sizes.append(((sizes[-1][0] + 1) // 2, (sizes[-1][1] + 1) // 2))
    pyramid = [np.empty((4, h * w), np.float32) for h, w in sizes]
    fills = [np.empty((3, h * w), np.float32) for h, w in sizes]
    for b in range(color.shape[0]):
        _finite_level(color[b], alpha[b, 0], pyramid[0])
        for k in range(1, len(sizes)):
            _pull(pyramid[k - 1], sizes[k - 1][0], sizes[k - 1][1], pyramid[k], sizes[k][0], sizes[k][1])
        top, fill = pyramid[-1], fills[-1]
        for c in range(3):
            fill[c, 0] = top[c, 0] / max(top[3, 0], eps) if top[3, 0] > eps else empty[c]
        for k in range(len(sizes) - 2, -1, -1):
            _push(pyramid[k], sizes[k][0], sizes[k][1], fills[k + 1], sizes[k + 1][0], sizes[k + 1][1], fills[k])
        out[b] = fills[0].reshape(3, height, width)


@_jit()
def _finite_level(color, alpha, level):
    """The first level (4, H*W) of one image: colour (3, H, W) with NaN and Inf as 0, alpha
    (H, W) with NaN as 0, clamped to [0, 1]."""
    h, w = alpha.shape
    zero, one = np.float32(0.0), np.float32(1.0)
    for c in range(3):
        for y in range(h):
            for x in range(w):
                v = color[c, y, x]
                level[c, y * w + x] = v if math.isfinite(v) else zero
    for y in range(h):
        for x in range(w):
            a = alpha[y, x]
            level[3, y * w + x] = zero if math.isnan(a) else min(max(a, zero), one)


@_jit()
def _pull(src, h0, w0, dst, h1, w1):
    """dst (4, h1*w1): the 2x2 window means of src (4, h0*w0), summed in the pooling's order;
    windows at odd edges average their valid pixels (``_halve``)."""
    quarter, half = np.float32(0.25), np.float32(0.5)
    for c in range(4):
        for y in range(h1):
            ra, rb = 2 * y * w0, min(2 * y + 1, h0 - 1) * w0
            for x in range(w1):
                xa, xb = 2 * x, min(2 * x + 1, w0 - 1)
                if rb > ra and xb > xa:
                    s = ((src[c, ra + xa] + src[c, ra + xb]) + src[c, rb + xa]) + src[c, rb + xb]
                    dst[c, y * w1 + x] = s * quarter
                elif rb > ra:
                    dst[c, y * w1 + x] = (src[c, ra + xa] + src[c, rb + xa]) * half
                elif xb > xa:
                    dst[c, y * w1 + x] = (src[c, ra + xa] + src[c, ra + xb]) * half
                else:
                    dst[c, y * w1 + x] = src[c, ra + xa]


@_jit()
def _push(level, h0, w0, below, h1, w1, out):
    """out (3, h0*w0): ``level``'s colour + (1 - its alpha) x the bilinear upsampling
    (align_corners=False, as ``_upsample``) of ``below`` (3, h1*w1)."""
    rows0, rows1, row_weights = _taps(h1, h0)
    cols0, cols1, col_weights = _taps(w1, w0)
    one = np.float32(1.0)
    for c in range(3):
        for y in range(h0):
            r0, r1, ly = rows0[y] * w1, rows1[y] * w1, row_weights[y]
            for x in range(w0):
                x0, x1, lx = cols0[x], cols1[x], col_weights[x]
                upper = (one - lx) * below[c, r0 + x0] + lx * below[c, r0 + x1]
                lower = (one - lx) * below[c, r1 + x0] + lx * below[c, r1 + x1]
                p = y * w0 + x
                out[c, p] = level[c, p] + (one - level[3, p]) * ((one - ly) * upper + ly * lower)


@_jit()
def _taps(n_in, n_out):
    """Bilinear resampling of ``n_in`` samples at ``n_out`` (align_corners=False): each output's
    two source indices and the second one's weight, in float32 as torch's CPU kernel."""
    first, second, weight = np.empty(n_out, np.int64), np.empty(n_out, np.int64), np.empty(n_out, np.float32)
    scale, half, zero = np.float32(n_in) / np.float32(n_out), np.float32(0.5), np.float32(0.0)
    for i in range(n_out):
        src = max(scale * (np.float32(i) + half) - half, zero)
        k = min(int(src), n_in - 1)
        first[i], second[i], weight[i] = k, min(k + 1, n_in - 1), src - np.float32(k)
    return first, second, weight
