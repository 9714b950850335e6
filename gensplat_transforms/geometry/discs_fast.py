"""Compiled (numba) twin of the RGB-D surface-disc rule in :mod:`.rgbd`.

The same per-pixel rule as ``rgbd._surface_step`` and ``rgbd._disc_shape`` (see the module
docstring of :mod:`.rgbd`), fused into one pass over each image row instead of some 150
full-image tensor operations, so that a dataloader worker can rebuild a timestep's
Gaussians from cached depth for every sample.

Each row is computed in blocks of pixels by a branch-free loop (every condition a select)
in float32 lanes only, which the compiler turns into SIMD code of the machine's full width;
the block is then copied out to the rows of the pixels with depth.

Numbers: computed in float32, arranged to stay accurate and finite at any depth. A pixel's
steps to its neighbours are taken in the camera frame in units of depth, from depth
differences: with r(u) = (u + 0.5 - cx) / fx the ray slope of column u and r_v that of the
row, (P(u+1) - P(u)) / z = (r(u+1) e + 1/fx, r_v e, e) where e = (z(u+1) - z) / z, so no
two nearly equal points are subtracted, and the disc shape works on numbers of order 1/f
whatever the depth (its scales are multiplied by z at the end); the in-plane angle comes
from half-angle formulas without cancellation. Covariances agree with a float64 evaluation
of the rule to about 1e-6 (relative), closer than the float32 PyTorch rule, against which
the tests hold them. The 1e-20 clamps of ``rgbd._disc_shape`` apply here to those
depth-relative numbers, so the discs scale with the depths (exactly, for a power-of-two
factor) instead of degenerating at sub-micrometre depths as the PyTorch rule's do.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..core.jit import _jit
from ..core.sh import C0

_F = np.float32
_TINY = 1e-20  # as in rgbd._disc_shape
_BLOCK = 256  # pixels of a row computed at once
_ROWS = 13  # outputs per pixel: mean 3, quaternion 4, scales 3, SH DC 3


@_jit(inline=True)
def _step(f0, f1, f2, zf, c0, c1, c2, zb, ob, t, fall0, fall1, k, edge_k):
    """Surface step along one image axis as ``rgbd._surface_step``, in units of the pixel's
    depth. Each pair's difference comes in units of its first pixel's depth: f, forward to
    the neighbour of depth ``zf``, in the pixel's; c, backward from the neighbour of depth
    ``zb``, in that neighbour's (``ob`` times the pixel's). Depths 0: none, -1: outside the
    image. ``t``: the squared stretch limit (max_stretch footprints, in units of the depth);
    (``fall0``, ``fall1``, 0): the fallback (the footprint along the axis). Times ``k``, or
    ``edge_k`` next to a depth edge. Where a difference is not finite (depths beyond
    float32's range) the step falls back. A depth edge is a step beyond the limit to a farther
    neighbour (the third components: f2 > 0, c2 < 0); a nearer one or no depth is none."""
    zero, inf = _F(0), _F(np.inf)
    nf = f0 * f0 + f1 * f1 + f2 * f2
    nc = c0 * c0 + c1 * c1 + c2 * c2
    nf = nf if zf > zero else inf
    nc = nc if zb > zero else inf
    edge = ((zf > zero) & (nf > t) & (f2 > zero)) | ((zb > zero) & (nc > t) & (c2 < zero))
    nb = nc * ob * ob if zb > zero else inf  # in units of the pixel's depth
    fwd = nf <= nb  # ties keep the forward step, as the reference
    ok = (nf if fwd else nb) <= t
    c = edge_k if edge else k
    s0 = (f0 if fwd else c0 * ob) if ok else fall0
    s1 = (f1 if fwd else c1 * ob) if ok else fall1
    s2 = (f2 if fwd else c2 * ob) if ok else zero
    return s0 * c, s1 * c, s2 * c


@_jit(inline=True)
def _quat(r00, r01, r02, r10, r11, r12, r20, r21, r22):
    """Unit quaternion w-x-y-z (w >= 0) of a rotation matrix, branch-free Shepperd: the row
    of the symmetric 4x4 matrix 4 q q^T with the largest diagonal entry, normalised."""
    zero, one = _F(0), _F(1)
    t0, t1 = one + r00 + r11 + r22, one + r00 - r11 - r22
    t2, t3 = one - r00 + r11 - r22, one - r00 - r11 + r22
    a, b, c = r21 - r12, r02 - r20, r10 - r01
    d, e, f = r01 + r10, r02 + r20, r12 + r21
    use0 = (t0 >= t1) & (t0 >= t2) & (t0 >= t3)
    use1 = (t1 >= t2) & (t1 >= t3)
    use2 = t2 >= t3
    w = t0 if use0 else (a if use1 else (b if use2 else c))
    x = a if use0 else (t1 if use1 else (d if use2 else e))
    y = b if use0 else (d if use1 else (t2 if use2 else f))
    z = c if use0 else (e if use1 else (f if use2 else t3))
    n = math.sqrt(w * w + x * x + y * y + z * z)
    good = n > _F(1e-8)
    g = (-one if w < zero else one) / (n if good else one)
    return w * g if good else one, x * g if good else zero, y * g if good else zero, z * g if good else zero


@_jit(inline=True)
def _row(ins, nb, buf, ryc, ryd, consts, cam):
    """Outputs of nb pixels of a row into the columns of ``buf`` (rows as ``_ROWS``). ``ins``:
    arrays zl, zc, zr, zu, zd, rl, rr, red, green, blue: pixel i has depth ``zc[i]``,
    neighbours ``zl[i]``, ``zr[i]`` (left, right), ``zu[i]``, ``zd[i]`` (up, down), ray slope
    ``rl[i]`` (``rr[i]``: its right neighbour's) and colour; ``ryc``, ``ryd``: ray slopes of
    the row and the next; ``consts`` and ``cam`` as in ``_discs``."""
    zl, zc, zr, zu, zd, rl, rr, red, green, blue = ins
    ifx, ify, ms, k, edge_k, sigma, thick = consts
    R00, R01, R02, t0, R10, R11, R12, t1, R20, R21, R22, t2 = cam
    zero, half, one, tiny, dc_scale = _F(0), _F(0.5), _F(1), _F(_TINY), _F(1 / C0)
    tu, tv = ms * ifx * ms * ifx, ms * ify * ms * ify  # squared limits in units of the depth
    for i in range(nb):
        d, lft, rgt, up, dn, rxc, rxr = zc[i], zl[i], zr[i], zu[i], zd[i], rl[i], rr[i]
        # relative depth steps of the pairs: forward in units of this depth, backward of the neighbour's
        iz = one / d
        er, ed, el, eu = (rgt - d) * iz, (dn - d) * iz, (d - lft) / lft, (d - up) / up
        a0, a1, a2 = _step(rxr * er + ifx, ryc * er, er, rgt, rxc * el + ifx, ryc * el, el, lft, lft * iz, tu,
                           ifx, zero, k, edge_k)  # fmt: skip
        b0, b1, b2 = _step(rxc * ed, ryd * ed + ify, ed, dn, rxc * eu, ryc * eu + ify, eu, up, up * iz, tv,
                           zero, ify, k, edge_k)  # fmt: skip
        # disc shape as rgbd._disc_shape: normal n, in-plane basis e1 = a / |a|, e2 = n x e1
        n0, n1, n2 = a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0
        nn = math.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
        inv = one / max(tiny, nn)
        n0, n1, n2 = n0 * inv, n1 * inv, n2 * inv
        la = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        la = max(tiny, la)
        lb = math.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
        inv = one / la
        e10, e11, e12 = a0 * inv, a1 * inv, a2 * inv
        e20, e21, e22 = n1 * e12 - n2 * e11, n2 * e10 - n0 * e12, n0 * e11 - n1 * e10
        bb1 = b0 * e10 + b1 * e11 + b2 * e12
        bb2 = b0 * e20 + b1 * e21 + b2 * e22
        g11, g12, g22 = la * la + bb1 * bb1, bb1 * bb2, bb2 * bb2
        dif, mid = half * (g11 - g22), half * (g11 + g22)
        rad = math.sqrt(dif * dif + g12 * g12)
        # cos and sin of phi = atan2(2 g12, g11 - g22) / 2: the larger one by the half-angle
        # formula without cancellation, the other from sin(2 phi) = 2 sin cos
        r = rad if rad > zero else one
        big = math.sqrt((r + abs(dif)) / (r + r))
        small = g12 / ((r + r) * big)
        c = (big if dif >= zero else abs(small)) if rad > zero else one
        s = (small if dif >= zero else (big if g12 >= zero else -big)) if rad > zero else zero
        # disc axes in the camera frame (columns u, v, n), then in the world: R_world = R @ R_cam
        u0, u1, u2 = c * e10 + s * e20, c * e11 + s * e21, c * e12 + s * e22
        v0, v1, v2 = c * e20 - s * e10, c * e21 - s * e11, c * e22 - s * e12
        buf[3, i], buf[4, i], buf[5, i], buf[6, i] = _quat(
            R00 * u0 + R01 * u1 + R02 * u2, R00 * v0 + R01 * v1 + R02 * v2, R00 * n0 + R01 * n1 + R02 * n2,
            R10 * u0 + R11 * u1 + R12 * u2, R10 * v0 + R11 * v1 + R12 * v2, R10 * n0 + R11 * n1 + R12 * n2,
            R20 * u0 + R21 * u1 + R22 * u2, R20 * v0 + R21 * v1 + R22 * v2, R20 * n0 + R21 * n1 + R22 * n2,
        )  # fmt: skip
        p0, p1 = rxc * d, ryc * d
        buf[0, i] = R00 * p0 + R01 * p1 + R02 * d + t0
        buf[1, i] = R10 * p0 + R11 * p1 + R12 * d + t1
        buf[2, i] = R20 * p0 + R21 * p1 + R22 * d + t2
        lo, sd = mid - rad, sigma * d
        buf[7, i] = sd * math.sqrt(mid + rad)
        buf[8, i] = sd * math.sqrt(max(zero, lo))
        buf[9, i] = thick * sd * min(la, lb)
        buf[10, i] = (red[i] - half) * dc_scale
        buf[11, i] = (green[i] - half) * dc_scale
        buf[12, i] = (blue[i] - half) * dc_scale


@_jit()
def _discs(zp, img, rx, ry, c2w, stride, consts, offset, start, means, quats, scales, dc, ids):
    """Fill rows ``start``.. of the (flattened) outputs, one per pixel with depth on the stride
    grid, from one view; returns the next free row.

    zp: (H + 2, W + 2) depth padded by one pixel of -1, 0 where none (see ``_pad``);
    img: (3, H, W); rx, ry: (W + 1,), (H + 1,) ray slopes (u + 0.5 - cx) / fx, (v + 0.5 - cy) / fy;
    c2w: (4, 4); consts: float32 1/fx, 1/fy, max_stretch, stride, stride * edge_scale,
    sigma_px, thickness; offset: pixel id of the view's first pixel.
    """
    h, w = zp.shape[0] - 2, zp.shape[1] - 2
    cam = (c2w[0, 0], c2w[0, 1], c2w[0, 2], c2w[0, 3], c2w[1, 0], c2w[1, 1], c2w[1, 2], c2w[1, 3],
           c2w[2, 0], c2w[2, 1], c2w[2, 2], c2w[2, 3])  # fmt: skip
    buf = np.empty((_ROWS, _BLOCK), np.float32)  # a constant shape: the compiler sees no overlaps
    cols = np.empty(_BLOCK, np.int64)
    src = np.empty((10, _BLOCK), np.float32)
    s0 = stride // 2  # first row and column of the grid
    nx = len(range(s0, w, stride))
    n = start
    for y in range(s0, h, stride):
        for b in range(0, nx, _BLOCK):
            nb = min(_BLOCK, nx - b)
            c = s0 + b * stride  # padded column left of the block's first pixel
            above, row, below = zp[y], zp[y + 1], zp[y + 2]
            red, green, blue = img[0, y], img[1, y], img[2, y]
            if stride == 1:  # contiguous views: SIMD loads
                ins = (row[c:], row[c + 1 :], row[c + 2 :], above[c + 1 :], below[c + 1 :], rx[c:], rx[c + 1 :],
                       red[c:], green[c:], blue[c:])  # fmt: skip
            else:  # gathered into contiguous rows
                for i in range(nb):
                    x = c + i * stride
                    src[0, i], src[1, i], src[2, i], src[3, i] = row[x], row[x + 1], row[x + 2], above[x + 1]
                    src[4, i], src[5, i], src[6, i] = below[x + 1], rx[x], rx[x + 1]
                    src[7, i], src[8, i], src[9, i] = red[x], green[x], blue[x]
                ins = (src[0], src[1], src[2], src[3], src[4], src[5], src[6], src[7], src[8], src[9])
            _row(ins, nb, buf, ry[y], ry[y + 1], consts, cam)
            cnt = 0  # move the columns of the pixels with depth to the front
            for i in range(nb):
                if row[c + 1 + i * stride] > _F(0):
                    if cnt < i:
                        for j in range(_ROWS):
                            buf[j, cnt] = buf[j, i]
                    cols[cnt] = c + i * stride
                    cnt += 1
            mo, qo, so, do, io = means[3 * n :], quats[4 * n :], scales[3 * n :], dc[3 * n :], ids[n:]
            for i in range(cnt):  # one loop per output: SIMD copies
                mo[3 * i], mo[3 * i + 1], mo[3 * i + 2] = buf[0, i], buf[1, i], buf[2, i]
            for i in range(cnt):
                qo[4 * i], qo[4 * i + 1], qo[4 * i + 2], qo[4 * i + 3] = (buf[3, i], buf[4, i], buf[5, i],
                                                                          buf[6, i])  # fmt: skip
            for i in range(cnt):
                so[3 * i], so[3 * i + 1], so[3 * i + 2] = buf[7, i], buf[8, i], buf[9, i]
            for i in range(cnt):
                do[3 * i], do[3 * i + 1], do[3 * i + 2] = buf[10, i], buf[11, i], buf[12, i]
            for i in range(cnt):
                io[i] = offset + y * w + cols[i]
            n += cnt
    return n


@_jit()
def _pad(z, stride):
    """Depths (V, H, W) padded by one pixel of -1 (outside the image), 0 where not > 0 (no
    depth); and the number of pixels with depth on the stride grid."""
    V, h, w = z.shape
    zp = np.full((V, h + 2, w + 2), _F(-1))
    n = 0
    for v in range(V):
        for y in range(h):
            for x in range(w):
                d = z[v, y, x]
                zp[v, y + 1, x + 1] = max(_F(0), d)
        for y in range(stride // 2, h, stride):
            for x in range(stride // 2, w, stride):
                n += zp[v, y + 1, x + 1] > _F(0)
    return zp, n


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
    V, H, W = depths.shape
    zp, n = _pad(depths.detach().cpu().float().contiguous().numpy(), stride)
    img = images.detach().cpu().float().contiguous().numpy()
    Kd, T = K.detach().cpu().double().numpy(), c2w.detach().cpu().float().contiguous().numpy()
    out = [np.empty((n, c), np.float32) for c in (3, 4, 3, 3)]
    ids = np.empty(n, np.int64)
    flat = [o.reshape(-1) for o in out]
    rest = tuple(_F(x) for x in (max_stretch, stride, stride * edge_scale, sigma_px, thickness))
    k = 0
    for v in range(V):
        fx, fy, cx, cy = Kd[v, 0, 0], Kd[v, 1, 1], Kd[v, 0, 2], Kd[v, 1, 2]
        rx = ((np.arange(W + 1) + 0.5 - cx) / fx).astype(np.float32)
        ry = ((np.arange(H + 1) + 0.5 - cy) / fy).astype(np.float32)
        consts = (_F(1 / fx), _F(1 / fy), *rest)
        k = _discs(zp[v], img[v], rx, ry, T[v], stride, consts, v * H * W, k, *flat, ids)
    return (*(torch.from_numpy(o) for o in out), torch.from_numpy(ids))


@_jit()
def _roughness(z, fu, fv, edge, window, out):
    """``rgbd.depth_roughness`` of one view's (H, W) float32 depth ``z`` into ``out`` (H, W),
    in float32, one row at a time: each row's |d| (both directions), d_u, d_v and count summed
    along the row over the window into a ring of ``window`` rows, whose running column sums
    give the window's sums."""
    h, w = z.shape
    zero, one, half = _F(0), _F(1), _F(0.5)
    inv = np.zeros((h, w), np.float32)
    for y in range(h):
        for x in range(w):
            if z[y, x] > 0:
                inv[y, x] = one / z[y, x]
    r = window // 2
    ring = np.zeros((window, 4, w), np.float32)  # per row: sums over x - r .. x + r of |d|, d_u, d_v, count
    per = np.zeros((4, w), np.float32)
    cols = np.zeros((4, w), np.float32)
    for y in range(h + r):
        if y < h:
            per[:] = zero  # branch-free along the row (SIMD): every condition a select
            for x in range(1, w - 1):
                c = inv[y, x]
                d = (inv[y, x - 1] + inv[y, x + 1] - (c + c)) * (z[y, x] * half * fu)
                ok = (c > zero) & (inv[y, x - 1] > zero) & (inv[y, x + 1] > zero) & (abs(d) < edge)
                per[0, x] = abs(d) if ok else zero
                per[1, x] = d if ok else zero
                per[3, x] = one if ok else zero
            if 0 < y < h - 1:
                for x in range(w):
                    c = inv[y, x]
                    d = (inv[y - 1, x] + inv[y + 1, x] - (c + c)) * (z[y, x] * half * fv)
                    ok = (c > zero) & (inv[y - 1, x] > zero) & (inv[y + 1, x] > zero) & (abs(d) < edge)
                    per[0, x] += abs(d) if ok else zero
                    per[2, x] = d if ok else zero
                    per[3, x] += one if ok else zero
            row = ring[y % window]
            for k in range(4):
                acc = zero
                for x in range(min(r, w)):
                    acc += per[k, x]
                for x in range(w):
                    if x + r < w:
                        acc += per[k, x + r]
                    row[k, x] = acc
                    if x - r >= 0:
                        acc -= per[k, x - r]
            cols += row
        yo = y - r  # the output row whose window is now complete
        if yo >= 0:
            for x in range(w):
                noise = max(cols[0, x] - abs(cols[1, x]) - abs(cols[2, x]), zero)
                out[yo, x] = noise / cols[3, x] if cols[3, x] > half else zero
            if yo - r >= 0:
                cols -= ring[(yo - r) % window]


def depth_roughness(z: torch.Tensor, K: torch.Tensor, edge: float, window: int) -> torch.Tensor:
    """Compiled twin of ``rgbd.depth_roughness``: (V, H, W) float32 roughness of (V, H, W)
    depth (0: none) with intrinsics K (V, 3, 3); ``edge`` and ``window`` as ``rgbd.ROUGH_EDGE``
    and ``ROUGH_WINDOW``."""
    zn = z.detach().cpu().float().contiguous().numpy()
    Kd = K.detach().cpu().double().numpy()
    out = np.empty(zn.shape, np.float32)
    for v in range(len(zn)):
        _roughness(zn[v], _F(Kd[v, 0, 0]), _F(Kd[v, 1, 1]), _F(edge), window, out[v])
    return torch.from_numpy(out)


@_jit()
def _soften(rho, z, fx, ids, hw, start, full, grow, saturation, scales, out):
    """``rgbd.soften`` of the discs at pixel ``ids`` (N,) from the flat roughness ``rho`` and
    depth ``z`` (V * H * W,), ``fx`` (V,) and ``hw`` = H * W: scales (N, 3) in place, each
    disc's saturation into ``out`` (N,); returns how many discs it softened."""
    span = 1.0 / (full - start)
    softened = 0
    for i in range(len(ids)):
        p = ids[i]
        blend = min(max((np.float64(rho[p]) - start) * span, 0.0), 1.0)
        if blend == 0:
            out[i] = saturation
            continue
        footprint = np.float64(z[p]) / fx[p // hw]
        extra = blend * grow * footprint * footprint
        s0, s1 = np.float64(scales[i, 0]), np.float64(scales[i, 1])
        scales[i, 0] = math.sqrt(s0 * s0 + extra)
        scales[i, 1] = math.sqrt(s1 * s1 + extra)
        out[i] = saturation - blend * (saturation - 1.0)
        softened += 1
    return softened


def soften_discs(z: torch.Tensor, K: torch.Tensor, pixel_ids: torch.Tensor, scales: torch.Tensor, edge: float,
                 window: int, start: float, full: float, grow: float,
                 saturation: float) -> torch.Tensor | None:  # fmt: skip
    """Compiled ``rgbd.rough_blend`` + ``rgbd.soften`` for the discs of :func:`surface_discs`:
    from (V, H, W) depth and (V, 3, 3) intrinsics, the discs at ``pixel_ids`` (N,) softened:
    ``scales`` (N, 3) (float32, contiguous, on the CPU, as :func:`surface_discs` makes them)
    changed in place, and their saturations (N,) float32 returned, or None where no disc is
    rough; ``grow``: the px^2 a fully rough disc's footprint gains; the rest as ``rgbd``'s
    ROUGH_* constants and ``saturation``."""
    if scales.dtype != torch.float32 or scales.device.type != "cpu" or not scales.is_contiguous():
        raise ValueError("soften_discs: scales must be a contiguous float32 CPU tensor (changed in place)")
    zn = z.detach().cpu().float().contiguous()
    rho = depth_roughness(zn, K, edge, window)
    out = np.empty(len(pixel_ids), np.float32)
    fx = K[:, 0, 0].detach().cpu().double().numpy()
    softened = _soften(rho.numpy().reshape(-1), zn.numpy().reshape(-1), fx, pixel_ids.numpy(),
                       zn.shape[1] * zn.shape[2], start, full, grow, saturation, scales.numpy(), out)  # fmt: skip
    return torch.from_numpy(out) if softened else None
