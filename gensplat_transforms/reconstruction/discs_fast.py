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
def _step(z, valid, h, w, y, x, dy, dx, ifx, ify, cx, cy, finv, p0, p1, p2, ax, max_stretch, edge_scale, s):
    """Surface step of pixel (y, x), camera point (p0, p1, p2), towards (dy, dx), in the camera
    frame (norms do not depend on the frame), times the stride ``s``. ``finv``: 1 / focal along
    the step, so a pixel's fronto-parallel footprint is z * finv; ``ax``: 0 (u) or 1 (v)."""
    best, edge = math.inf, False
    o0 = o1 = o2 = 0.0
    for sign in (1, -1):  # forward first: ties keep the forward step, as the reference
        yn, xn = y + sign * dy, x + sign * dx
        if yn < 0 or xn < 0 or yn >= h or xn >= w:
            continue
        if not valid[yn, xn]:
            edge = True
            continue
        d = z[yn, xn]
        q0, q1, q2 = (xn + 0.5 - cx) * ifx * d, (yn + 0.5 - cy) * ify * d, d
        d0, d1, d2 = (q0 - p0, q1 - p1, q2 - p2) if sign == 1 else (p0 - q0, p1 - q1, p2 - q2)
        n = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if n > max_stretch * (p2 if sign == 1 else d) * finv:  # the pair's first pixel's footprint
            edge = True
        if n < best:
            best, o0, o1, o2 = n, d0, d1, d2
    fp = p2 * finv
    if not best <= max_stretch * fp:
        o0, o1, o2 = (fp, 0.0, 0.0) if ax == 0 else (0.0, fp, 0.0)
    k = s * (edge_scale if edge else 1.0)
    return o0 * k, o1 * k, o2 * k


@_jit(inline=True)
def _quat(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Unit quaternion w-x-y-z (w >= 0) of a rotation matrix (Shepperd, largest diagonal)."""
    tr = r00 + r11 + r22
    if tr >= r00 and tr >= r11 and tr >= r22:
        s = math.sqrt(max(1 + tr, 1e-12)) * 2
        i = 1 / s
        w, x, y, z = s / 4, (r21 - r12) * i, (r02 - r20) * i, (r10 - r01) * i
    elif r00 >= r11 and r00 >= r22:
        s = math.sqrt(max(1 + r00 - r11 - r22, 1e-12)) * 2
        i = 1 / s
        w, x, y, z = (r21 - r12) * i, s / 4, (r01 + r10) * i, (r02 + r20) * i
    elif r11 >= r22:
        s = math.sqrt(max(1 - r00 + r11 - r22, 1e-12)) * 2
        i = 1 / s
        w, x, y, z = (r02 - r20) * i, (r01 + r10) * i, s / 4, (r12 + r21) * i
    else:
        s = math.sqrt(max(1 - r00 - r11 + r22, 1e-12)) * 2
        i = 1 / s
        w, x, y, z = (r10 - r01) * i, (r02 + r20) * i, (r12 + r21) * i, s / 4
    n = math.sqrt(w * w + x * x + y * y + z * z)
    if not n > 1e-8:
        return 1.0, 0.0, 0.0, 0.0
    f = (-1.0 if w < 0 else 1.0) / n
    return w * f, x * f, y * f, z * f


@_jit()
def _discs(z, valid, rgb, intr, rot, trans, stride, sigma, thickness, max_stretch, edge_scale, offset, start,
           means, quats, scales, dc, ids):
    """Fill rows ``start``.. of the outputs (one per valid pixel on the stride grid); returns the
    next free row. All geometry in the camera frame, rotated into the world at the end."""
    h, w = z.shape
    fx, fy, cx, cy = intr[0], intr[1], intr[2], intr[3]
    ifx, ify = 1.0 / fx, 1.0 / fy
    R00, R01, R02, R10, R11, R12, R20, R21, R22 = (rot[0, 0], rot[0, 1], rot[0, 2], rot[1, 0], rot[1, 1],
                                                   rot[1, 2], rot[2, 0], rot[2, 1], rot[2, 2])  # fmt: skip
    k = start
    for y in range(stride // 2, h, stride):
        for x in range(stride // 2, w, stride):
            if not valid[y, x]:
                continue
            d = z[y, x]
            p0, p1, p2 = (x + 0.5 - cx) * ifx * d, (y + 0.5 - cy) * ify * d, d
            a0, a1, a2 = _step(z, valid, h, w, y, x, 0, 1, ifx, ify, cx, cy, ifx, p0, p1, p2, 0, max_stretch,
                               edge_scale, stride)  # fmt: skip
            b0, b1, b2 = _step(z, valid, h, w, y, x, 1, 0, ifx, ify, cx, cy, ify, p0, p1, p2, 1, max_stretch,
                               edge_scale, stride)  # fmt: skip
            n0, n1, n2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
            inv = 1 / max(math.sqrt(n0 * n0 + n1 * n1 + n2 * n2), _TINY)
            n0, n1, n2 = n0 * inv, n1 * inv, n2 * inv
            la = max(math.sqrt(a0 * a0 + a1 * a1 + a2 * a2), _TINY)
            lb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
            e10, e11, e12 = a0 / la, a1 / la, a2 / la
            e20, e21, e22 = n1 * e12 - n2 * e11, n2 * e10 - n0 * e12, n0 * e11 - n1 * e10
            bb1 = b0 * e10 + b1 * e11 + b2 * e12
            bb2 = b0 * e20 + b1 * e21 + b2 * e22
            g11, g12, g22 = la * la + bb1 * bb1, bb1 * bb2, bb2 * bb2
            mid, rad = 0.5 * (g11 + g22), math.sqrt((0.5 * (g11 - g22)) ** 2 + g12 * g12)
            c, s = 1.0, 0.0  # cos and sin of phi = atan2(2 g12, g11 - g22) / 2, by half angles
            if rad > 0:
                c2 = 0.5 * (g11 - g22) / rad
                c, s = math.sqrt(max(0.5 * (1 + c2), 0.0)), math.copysign(math.sqrt(max(0.5 * (1 - c2), 0.0)), g12)
            # disc axes in the camera frame (columns), then in the world: R_world = rot @ R_cam
            u0, u1, u2 = c * e10 + s * e20, c * e11 + s * e21, c * e12 + s * e22
            v0, v1, v2 = c * e20 - s * e10, c * e21 - s * e11, c * e22 - s * e12
            qw, qx, qy, qz = _quat(
                R00 * u0 + R01 * u1 + R02 * u2, R00 * v0 + R01 * v1 + R02 * v2, R00 * n0 + R01 * n1 + R02 * n2,
                R10 * u0 + R11 * u1 + R12 * u2, R10 * v0 + R11 * v1 + R12 * v2, R10 * n0 + R11 * n1 + R12 * n2,
                R20 * u0 + R21 * u1 + R22 * u2, R20 * v0 + R21 * v1 + R22 * v2, R20 * n0 + R21 * n1 + R22 * n2,
            )  # fmt: skip
            for i in range(3):
                means[k, i] = rot[i, 0] * p0 + rot[i, 1] * p1 + rot[i, 2] * p2 + trans[i]
                dc[k, i] = (rgb[y, x, i] - 0.5) / C0
            quats[k, 0], quats[k, 1], quats[k, 2], quats[k, 3] = qw, qx, qy, qz
            scales[k, 0] = sigma * math.sqrt(mid + rad)
            scales[k, 1] = sigma * math.sqrt(max(mid - rad, 0.0))
            scales[k, 2] = thickness * sigma * min(la, lb)
            ids[k] = offset + y * w + x
            k += 1
    return k


def surface_discs(
    depths: torch.Tensor, images: torch.Tensor, K: torch.Tensor, c2w: torch.Tensor, stride: int, sigma_px: float,
    thickness: float, max_stretch: float, edge_scale: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Disc Gaussians of V views.

    Args:
        depths: (V, H, W) camera-z depth, 0 where no disc; images: (V, 3, H, W) in [0, 1];
        K: (V, 3, 3) intrinsics; c2w: (V, 4, 4) camera-to-world; the rest as in ``RGBDConfig``.
    Returns:
        means (N, 3), quats (N, 4), scales (N, 3), SH DC (N, 3), all float32, and pixel ids
        (N,) int64 (``view * H * W + row * W + col``), for the N pixels with depth on the
        stride grid, view by view in row-major order.
    """
    z = np.ascontiguousarray(depths.detach().cpu().numpy(), dtype=np.float32)
    ok = z > 0
    col = np.ascontiguousarray(images.detach().cpu().permute(0, 2, 3, 1).numpy(), dtype=np.float32)
    Kd, T = K.detach().cpu().double().numpy(), c2w.detach().cpu().double().numpy()
    V, H, W = z.shape
    s = stride // 2
    n = int(ok[:, s::stride, s::stride].sum())
    out = [np.empty((n, c), np.float32) for c in (3, 4, 3, 3)]
    ids = np.empty(n, np.int64)
    k = 0
    for v in range(V):
        intr = np.array([Kd[v, 0, 0], Kd[v, 1, 1], Kd[v, 0, 2], Kd[v, 1, 2]])
        k = _discs(z[v], ok[v], col[v], intr, np.ascontiguousarray(T[v, :3, :3]), np.ascontiguousarray(T[v, :3, 3]),
                   stride, sigma_px, thickness, max_stretch, edge_scale, v * H * W, k, *out, ids)  # fmt: skip
    return (*(torch.from_numpy(o) for o in out), torch.from_numpy(ids))
