"""Differentiable reference rasterizer in pure PyTorch (pair list + segmented scan).

Every (splat, pixel) pair inside a splat's box is listed, pairs failing the footprint or
alpha rules are dropped, the rest are sorted by pixel (stable, so each pixel's pairs stay
front to back) and composited with a segmented cumulative sum of log(1 - alpha).
Splats are processed in depth-ordered chunks of at most ``max_pairs`` box pairs, carrying
each pixel's transmittance from chunk to chunk, so memory stays bounded for any scene.
"""

from __future__ import annotations

import torch

from .projection import ALPHA_MAX, ALPHA_MIN, SIGMA_EXTENT, T_MIN, Projected


def _chunks(counts: torch.Tensor, max_pairs: int) -> list[tuple[int, int]]:
    """Split consecutive splats into runs whose box-pair totals stay under ``max_pairs``."""
    ends = torch.cumsum(counts, 0)
    bounds, start, base = [], 0, 0
    n = counts.shape[0]
    while start < n:
        stop = int(torch.searchsorted(ends, base + max_pairs, right=True))
        stop = max(stop, start + 1)  # a splat larger than the budget gets its own chunk
        bounds.append((start, stop))
        base = int(ends[stop - 1])
        start = stop
    return bounds


def rasterize_reference(
    proj: Projected,
    width: int,
    height: int,
    background: torch.Tensor,
    max_pairs: int = 1 << 22,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite projected splats front to back.

    Returns:
        rgb: (H*W, 3) including the background, depth_sum: (H*W,) sum of w_i z_i,
        alpha: (H*W,) accumulated opacity 1 - T.
    """
    dtype = proj.means2d.dtype
    device = proj.means2d.device
    npix = width * height
    rgb = torch.zeros(npix, 3, dtype=dtype, device=device)
    depth = torch.zeros(npix, dtype=dtype, device=device)
    log_t = torch.zeros(npix, dtype=torch.float64, device=device)  # log transmittance
    stopped = torch.zeros(npix, dtype=torch.bool, device=device)  # stop rule met in a chunk

    x0, y0, x1, y1 = proj.boxes.unbind(-1)
    bw, bh = x1 - x0 + 1, y1 - y0 + 1
    counts = bw * bh
    for s, e in _chunks(counts, max_pairs):
        cnt = counts[s:e]
        gid = torch.repeat_interleave(torch.arange(s, e, device=device), cnt)
        first = torch.cumsum(cnt, 0) - cnt
        local = torch.arange(gid.shape[0], device=device) - first.repeat_interleave(cnt)
        px = x0[gid] + local % bw[gid]
        py = y0[gid] + local // bw[gid]

        d = torch.stack([px, py], -1).to(dtype) + 0.5 - proj.means2d[gid]
        A, B, C = proj.conics[gid].unbind(-1)
        q = A * d[:, 0] ** 2 + 2 * B * d[:, 0] * d[:, 1] + C * d[:, 1] ** 2
        alpha = (proj.opacities[gid] * torch.exp(-0.5 * q)).clamp(max=ALPHA_MAX)
        ok = (q <= SIGMA_EXTENT**2) & (alpha >= ALPHA_MIN)
        gid, alpha = gid[ok], alpha[ok]
        pix = (py * width + px)[ok]
        if pix.numel() == 0:
            continue

        pix, order = torch.sort(pix, stable=True)  # stable: front-to-back within a pixel
        gid, alpha = gid[order], alpha[order]
        log1m = torch.log1p(-alpha.to(torch.float64))
        incl = torch.cumsum(log1m, 0)
        seg_start = torch.ones_like(pix, dtype=torch.bool)
        seg_start[1:] = pix[1:] != pix[:-1]
        # cumsum value just before each segment starts, broadcast over the segment
        before = (incl - log1m)[seg_start]
        seg_id = torch.cumsum(seg_start.long(), 0) - 1
        excl = incl - log1m - before[seg_id] + log_t[pix]
        # Stop rule: a pixel takes a splat only if its transmittance stays >= T_MIN after it.
        take = ((excl + log1m) >= torch.log(torch.tensor(T_MIN, dtype=torch.float64))) & ~stopped[pix]
        stopped[pix[~take]] = True
        w = (alpha * torch.exp(excl).to(dtype)) * take
        rgb = rgb.index_add(0, pix, w[:, None] * proj.colors[gid])
        depth = depth.index_add(0, pix, w * proj.depths[gid])
        log_t = log_t.index_add(0, pix, log1m * take)

    trans = torch.exp(log_t).to(dtype)
    rgb = rgb + trans[:, None] * background.to(dtype)
    return rgb, depth, 1.0 - trans
