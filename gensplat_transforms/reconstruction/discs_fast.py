"""Compiled (numba) twin of the RGB-D surface-disc rule in :mod:`.rgbd`.

The same per-pixel arithmetic as ``rgbd._surface_step`` and ``rgbd._disc_shape`` (see
the module docstring of :mod:`.rgbd` for the rule), fused into one pass over the pixels of
a view instead of some 150 full-image tensor operations: this is what lets a dataloader
worker rebuild a timestep's Gaussians from cached depth for every sample (two 224x224
views: a few milliseconds instead of about 100 on one thread). Computed in float64 and
returned in float32; tests hold it against the PyTorch rule.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..rendering.fast import _jit
from ..sh import C0

_TINY = 1e-20


@_jit(inline=True)
def _step(pts, valid, fp, h, w, y, x, dy, dx, axis, max_stretch, edge_scale, s, out):
    """One surface step of pixel (y, x) towards (dy, dx), times the stride ``s``, into ``out``."""
    best = math.inf
    edge = False
    for sign in (1, -1):  # forward first: ties keep the forward step, as the reference
        y0, x0 = (y, x) if sign == 1 else (y - dy, x - dx)  # the pair (y0, x0) -> (y0 + dy, x0 + dx)
        y1, x1 = y0 + dy, x0 + dx
        if y0 < 0 or x0 < 0 or y1 >= h or x1 >= w:
            continue
        if not (valid[y0, x0] and valid[y1, x1]):
            edge = True
            continue
        d0 = pts[y1, x1, 0] - pts[y0, x0, 0]
        d1 = pts[y1, x1, 1] - pts[y0, x0, 1]
        d2 = pts[y1, x1, 2] - pts[y0, x0, 2]
        n = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if n > max_stretch * fp[y0, x0]:
            edge = True
        if n < best:
            best = n
            out[0], out[1], out[2] = d0, d1, d2
    if not best <= max_stretch * fp[y, x]:
        out[0], out[1], out[2] = fp[y, x] * axis[0], fp[y, x] * axis[1], fp[y, x] * axis[2]
    k = s * (edge_scale if edge else 1.0)
    out[0] *= k
    out[1] *= k
    out[2] *= k


@_jit(inline=True)
def _quat(r, q):
    """Unit quaternion w-x-y-z (w >= 0) of the 3x3 rotation ``r`` (Shepperd, largest diagonal)."""
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    case, big = 0, tr
    for i in range(3):
        if r[i, i] > big:
            case, big = i + 1, r[i, i]
    if case == 0:
        s = math.sqrt(max(1 + tr, 1e-12)) * 2
        i = 1 / s
        q[0], q[1], q[2], q[3] = s / 4, (r[2, 1] - r[1, 2]) * i, (r[0, 2] - r[2, 0]) * i, (r[1, 0] - r[0, 1]) * i
    elif case == 1:
        s = math.sqrt(max(1 + r[0, 0] - r[1, 1] - r[2, 2], 1e-12)) * 2
        i = 1 / s
        q[0], q[1], q[2], q[3] = (r[2, 1] - r[1, 2]) * i, s / 4, (r[0, 1] + r[1, 0]) * i, (r[0, 2] + r[2, 0]) * i
    elif case == 2:
        s = math.sqrt(max(1 - r[0, 0] + r[1, 1] - r[2, 2], 1e-12)) * 2
        i = 1 / s
        q[0], q[1], q[2], q[3] = (r[0, 2] - r[2, 0]) * i, (r[0, 1] + r[1, 0]) * i, s / 4, (r[1, 2] + r[2, 1]) * i
    else:
        s = math.sqrt(max(1 - r[0, 0] - r[1, 1] + r[2, 2], 1e-12)) * 2
        i = 1 / s
        q[0], q[1], q[2], q[3] = (r[1, 0] - r[0, 1]) * i, (r[0, 2] + r[2, 0]) * i, (r[1, 2] + r[2, 1]) * i, s / 4
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if n > 1e-8:
        f = (-1.0 if q[0] < 0 else 1.0) / n
        for k in range(4):
            q[k] *= f
    else:
        q[0], q[1], q[2], q[3] = 1.0, 0.0, 0.0, 0.0


@_jit()
def _discs(z, valid, rgb, intr, rot, trans, stride, sigma, thickness, max_stretch, edge_scale, offset,
           means, quats, scales, dc, ids):
    """Fill the outputs (rows 0..n-1, n = valid pixels on the stride grid); see module docstring."""
    h, w = z.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    pts = np.empty((h, w, 3))
    fpu = np.empty((h, w))
    fpv = np.empty((h, w))
    for y in range(h):
        for x in range(w):
            d = z[y, x]
            cam0, cam1 = (x + 0.5 - cx) / fx * d, (y + 0.5 - cy) / fy * d
            for i in range(3):
                pts[y, x, i] = rot[i, 0] * cam0 + rot[i, 1] * cam1 + rot[i, 2] * d + trans[i]
            fpu[y, x], fpv[y, x] = d / fx, d / fy
    ax_u, ax_v = rot[:, 0].copy(), rot[:, 1].copy()
    a, b, n, e1, e2 = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    r, q = np.empty((3, 3)), np.empty(4)
    k = 0
    for y in range(stride // 2, h, stride):
        for x in range(stride // 2, w, stride):
            if not valid[y, x]:
                continue
            _step(pts, valid, fpu, h, w, y, x, 0, 1, ax_u, max_stretch, edge_scale, stride, a)
            _step(pts, valid, fpv, h, w, y, x, 1, 0, ax_v, max_stretch, edge_scale, stride, b)
            n[0], n[1], n[2] = a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]
            nn = max(math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), _TINY)
            la = max(math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]), _TINY)
            lb = math.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
            for i in range(3):
                n[i] /= nn
                e1[i] = a[i] / la
            e2[0], e2[1], e2[2] = n[1] * e1[2] - n[2] * e1[1], n[2] * e1[0] - n[0] * e1[2], n[0] * e1[1] - n[1] * e1[0]
            b1 = b[0] * e1[0] + b[1] * e1[1] + b[2] * e1[2]
            b2 = b[0] * e2[0] + b[1] * e2[1] + b[2] * e2[2]
            g11, g12, g22 = la * la + b1 * b1, b1 * b2, b2 * b2
            mid, rad = 0.5 * (g11 + g22), math.sqrt((0.5 * (g11 - g22)) ** 2 + g12 * g12)
            c, s = 1.0, 0.0  # cos and sin of phi = atan2(2 g12, g11 - g22) / 2, by half angles
            if rad > 0:
                c2 = 0.5 * (g11 - g22) / rad
                c, s = math.sqrt(max(0.5 * (1 + c2), 0.0)), math.copysign(math.sqrt(max(0.5 * (1 - c2), 0.0)), g12)
            for i in range(3):
                r[i, 0], r[i, 1], r[i, 2] = c * e1[i] + s * e2[i], c * e2[i] - s * e1[i], n[i]
            _quat(r, q)
            for i in range(3):
                means[k, i] = pts[y, x, i]
                dc[k, i] = (rgb[y, x, i] - 0.5) / C0
            for i in range(4):
                quats[k, i] = q[i]
            scales[k, 0] = sigma * math.sqrt(mid + rad)
            scales[k, 1] = sigma * math.sqrt(max(mid - rad, 0.0))
            scales[k, 2] = thickness * sigma * min(la, lb)
            ids[k] = offset + y * w + x
            k += 1


def surface_discs(
    depth: torch.Tensor, valid: torch.Tensor, rgb: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor,
    stride: int, sigma_px: float, thickness: float, max_stretch: float, edge_scale: float, offset: int = 0,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Disc Gaussians of one view.

    Args:
        depth: (H, W) camera-z depth; valid: (H, W) bool; rgb: (3, H, W) in [0, 1];
        K: (3, 3) intrinsics; c2w: (4, 4) camera-to-world; the rest as in ``RGBDConfig``;
        offset: added to the pixel ids (``view * H * W``).
    Returns:
        means (N, 3), quats (N, 4), scales (N, 3), SH DC (N, 3), all float32, and pixel ids
        (N,) int64, for the N valid pixels on the stride grid, in row-major order.
    """
    z = np.ascontiguousarray(depth.detach().cpu().numpy(), dtype=np.float32)
    ok = np.ascontiguousarray(valid.detach().cpu().numpy(), dtype=np.bool_)
    col = np.ascontiguousarray(rgb.detach().cpu().permute(1, 2, 0).numpy(), dtype=np.float32)
    Kd, T = K.detach().cpu().double().numpy(), c2w.detach().cpu().double().numpy()
    intr = np.array([Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]])
    s = stride // 2
    n = int(ok[s::stride, s::stride].sum())
    out = [np.empty((n, c), np.float32) for c in (3, 4, 3, 3)]
    ids = np.empty(n, np.int64)
    _discs(z, ok, col, intr, np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3]), stride,
           sigma_px, thickness, max_stretch, edge_scale, offset, *out, ids)  # fmt: skip
    return (*(torch.from_numpy(o) for o in out), torch.from_numpy(ids))

