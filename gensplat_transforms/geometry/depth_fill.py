"""Small holes of a depth sensor's map filled from around, before the discs are built.

A real RGB-D camera leaves pixels without depth where its two imagers disagree: a band
beside foreground edges (the stereo occlusion shadow), dark surfaces with little infrared
return, the edge pixels its filters drop. The RGB-D path makes no disc there, so even at
the source pose those pixels show what is behind or the hole filling's guess, although the
image has their colour. :func:`fill_depth` fills them from their edges inward, a pixel a
round for ``steps`` rounds: each pixel without depth next to depth takes the farthest depth
among its four neighbours (the rule of librealsense's hole-filling filter, "farthest from
around": a guess too far hides behind the true surface instead of floating in front of it),
and every filled pixel is then put ``BEHIND`` times farther along its ray, so that where its
disc meets a measured surface seen from a moved camera, the measured one is in front.
Holes wider than twice ``steps`` keep their centres empty.

Why 3 %: docs/reconstruction.md.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.jit import _jit

#: filled depth is put this much farther than the depth around it (see the module docstring)
BEHIND = 1.03


@_jit()
def _fill(z, steps):
    """Fill ``z`` (n, H, W) float32 in place: ``steps`` rounds, each giving every pixel <= 0
    the largest of its 4-neighbours' depths of the round before (when one is > 0)."""
    n, H, W = z.shape
    for i in range(n):
        holes = np.argwhere(z[i] <= 0)
        for _ in range(steps):
            if holes.shape[0] == 0:
                break
            found = np.zeros(holes.shape[0], np.float32)
            for k in range(holes.shape[0]):
                r, c = holes[k, 0], holes[k, 1]
                best = np.float32(0)
                if r > 0:
                    best = max(best, z[i, r - 1, c])
                if r < H - 1:
                    best = max(best, z[i, r + 1, c])
                if c > 0:
                    best = max(best, z[i, r, c - 1])
                if c < W - 1:
                    best = max(best, z[i, r, c + 1])
                found[k] = best
            left = 0
            for k in range(holes.shape[0]):  # written after the round: a round grows one pixel
                if found[k] > 0:
                    z[i, holes[k, 0], holes[k, 1]] = found[k]
                else:
                    holes[left] = holes[k]
                    left += 1
            if left == holes.shape[0]:  # nothing filled: no later round can fill more (no depth in reach)
                break
            holes = holes[:left]


def fill_depth(depth: torch.Tensor, steps: int) -> torch.Tensor:
    """(..., H, W) depth, 0 where none (as ``RGBDReconstructor.clean_depth`` gives it), with
    the pixels within ``steps`` 4-connected steps of depth filled, ``BEHIND`` the depth around
    them (see the module docstring); float32, on ``depth``'s device. ``steps`` 0 returns it
    unchanged.

    Example: a one-pixel hole takes the farther of its neighbours, 3 % behind it
        >>> z = torch.tensor([[1.0, 0.0, 2.0]])
        >>> fill_depth(z, 1)
        tensor([[1.0000, 2.0600, 2.0000]])
    """
    if steps < 0:
        raise ValueError(f"fill_depth: steps must be >= 0, got {steps}")
    if steps == 0 or not (depth <= 0).any():
        return depth
    measured = depth.detach().to("cpu", torch.float32).reshape(-1, *depth.shape[-2:]).contiguous()
    z = measured.clone()
    _fill(z.numpy(), int(steps))
    z = torch.where(measured > 0, measured, z * BEHIND)
    return z.reshape(depth.shape).to(depth.device)
