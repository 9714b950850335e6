"""Forward warping of RGB-D views: the baseline that rendering Gaussians must beat.

Every source pixel with a depth is lifted to its 3D point, projected into the target camera
and written to the pixel it lands in (nearest pixel, no splatting); where several land in
one pixel the nearest to the target camera wins (a z-buffer). Pixels nothing lands in stay
empty: no Gaussians, no footprints, no hole filling.
"""

from __future__ import annotations

import torch

from ..core.cameras import Cameras
from ..geometry.base import valid_depth


def forward_warp(
    images: torch.Tensor, depths: torch.Tensor, cameras: Cameras, target: Cameras
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward-warp V RGB-D views into B target cameras (module docstring).

    Args:
        images: (V, 3, H, W) colours; depths: (V, 1, H, W) metric camera-z depth (pixels
            without depth as in :func:`~.geometry.base.valid_depth` are skipped);
        cameras: the V source cameras (H x W); target: B cameras of any image size.
    Returns:
        rgb: (B, 3, H', W') in ``images``' dtype, 0 where nothing landed;
        mask: (B, 1, H', W') bool, the pixels some source pixel landed in.
    """
    v, dev = images.shape[0], images.device
    dtype = cameras.dtype
    z = depths.reshape(v, -1).to(dtype)
    keep = valid_depth(z)
    uv = cameras.pixel_centers()[None].expand(v, -1, -1)
    points = cameras.unproject(uv, torch.where(keep, z, torch.ones_like(z)))[keep]  # (N, 3)
    colours = images.permute(0, 2, 3, 1).reshape(v, -1, 3)[keep]  # (N, 3)

    b, h, w = len(target), target.height, target.width
    uv, zt = target.to(dev, dtype).project(points)  # (B, N, 2), (B, N)
    lands = (zt > 0) & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    col, row = (uv[..., i].where(lands, torch.zeros_like(zt)).floor().long() for i in (0, 1))
    pixel = ((torch.arange(b, device=dev)[:, None] * h + row) * w + col)[lands]
    source = torch.arange(points.shape[0], device=dev).expand(b, -1)[lands]
    zt = zt[lands]

    zbuf = torch.full((b * h * w,), torch.inf, dtype=dtype, device=dev).scatter_reduce(0, pixel, zt, "amin")
    front = zt == zbuf[pixel]
    winner = torch.full((b * h * w,), -1, device=dev).scatter_reduce(0, pixel[front], source[front], "amax")
    mask = winner >= 0
    rgb = torch.zeros(b * h * w, 3, dtype=images.dtype, device=dev)
    rgb[mask] = colours[winner[mask]]
    return rgb.reshape(b, h, w, 3).permute(0, 3, 1, 2), mask.reshape(b, 1, h, w)
