"""Fast CPU inference backend ("fast"): projection and tile rasterization compiled with numba.

Same rules and outputs as :mod:`.projection` + :mod:`.reference` (see projection.py), not
differentiable. One frame runs in three compiled stages:

1. projection, in float64 like ``project()``: cull (near plane, opacity), EWA conic and
   opacity-aware pixel box per Gaussian; the visible ones are sorted front to back with a
   stable radix sort on the depth bits, and their colours are evaluated from SH (only up to
   the requested degree) into one packed record per splat;
2. binning: each splat is listed in the 16x16 tiles its box touches, keeping depth order;
3. rasterization, tile by tile with the Gaussian-outer loop: each splat visits only the
   rows of its box inside the tile that still have live pixels (one bit mask per row), and
   evaluates a whole 16-pixel tile row at once, branch-free, so the compiler can use SIMD
   (the exponential is a polynomial for that reason). A pixel stops at the splat that would
   take its transmittance below 1e-4; a tile stops when all its pixels have; tiles without
   splats are only filled with the background.

Numbers: float64 inputs render in float64, any other float dtype in float32. Per pair the
float arithmetic follows the reference operation by operation except the exponential
(relative error below 1e-6) and the transmittance (a running float product instead of a
float64 log sum), so images agree to about 1e-6.

Threads: ``threads=1`` (the default, one dataloader worker = one thread) runs serial
compiled code that never starts numba's thread pool, so it is safe in forked workers;
``threads=n > 1`` runs the parallel version on ``min(n, numba.config.NUMBA_NUM_THREADS)``
threads and restores numba's thread count afterwards. The image does not depend on the
thread count.

Compiled code is cached on disk (``cache=True``), so a new process loads it in well under
a second instead of compiling. numba writes the cache to ``__pycache__`` next to this file,
falls back to a per-user cache directory when that is read-only, and uses
``NUMBA_CACHE_DIR`` when set (set it in read-only deployments, e.g. containers); when no
location is writable the functions are compiled in each process.
"""

from __future__ import annotations

import math
import time
from contextlib import contextmanager, nullcontext

import numba
import numpy as np
import torch
from numba import prange

from ..cameras import Cameras
from ..gaussians import Gaussians
from ..sh import sh_degree_from_bases
from .projection import ALPHA_MAX, ALPHA_MIN, DILATION, FOV_CLAMP, MAX_SCALE, SIGMA_EXTENT, T_MIN

TILE = 16  # tile side in pixels: one tile row is one 16-lane vector
# packed per-splat record (float): u, v, A, 2B, C, opacity, r, g, b, depth
_U, _V, _A, _B2, _C, _O, _R, _G, _BL, _Z = range(10)
_REC = 10
# above this opacity the box extent is 3 sigma: 2 ln(255 o) > 9 (0.353 < 0.36)
_OPAC_FULL_EXTENT = 0.36


def _jit(parallel: bool = False):
    """``njit`` with an on-disk cache; without a writable cache location, no cache."""

    def wrap(fn):
        try:
            return numba.njit(cache=True, parallel=parallel, error_model="numpy")(fn)
        except RuntimeError:  # numba found no writable cache directory
            return numba.njit(cache=False, parallel=parallel, error_model="numpy")(fn)

    return wrap


# --------------------------------------------------------------------------- projection
@_jit()
def _project_one(i, means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height, rec, boxes, keys):
    """Project Gaussian i with projection.py's rules in float64 (up to rounding: products
    with reciprocals instead of some divisions). Culled: keys[i] = inf. Otherwise keys[i] is
    its depth, boxes[i] its pixel box (x0, y0, x1, y1) and rec[i] its record, rounded to
    rec's dtype as ``.to(out_dtype)`` does.

    cam: (23,) float64: world-to-camera rows (12), fx, fy, cx, cy, the field-of-view clamp
        limits for x/z (+, -) and y/z (+, -), camera centre (3).
    """
    keys[i] = np.inf
    o = np.float64(opacities[i])
    mx, my, mz = np.float64(means[i, 0]), np.float64(means[i, 1]), np.float64(means[i, 2])
    z = cam[8] * mx + cam[9] * my + cam[10] * mz + cam[11]
    if not (z > near and o >= opac_min):
        return
    x = cam[0] * mx + cam[1] * my + cam[2] * mz + cam[3]
    y = cam[4] * mx + cam[5] * my + cam[6] * mz + cam[7]
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    iz = 1.0 / z

    # rows of J W (2x3): J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]] with the field-of-view
    # clamp on tx = x/z, ty = y/z; W = camera rotation
    tx = min(max(x * iz, -cam[17]), cam[16])
    ty = min(max(y * iz, -cam[19]), cam[18])
    j00, j02, j11, j12 = fx * iz, -fx * tx * iz, fy * iz, -fy * ty * iz
    a0, a1, a2 = j00 * cam[0] + j02 * cam[8], j00 * cam[1] + j02 * cam[9], j00 * cam[2] + j02 * cam[10]
    b0, b1, b2 = j11 * cam[4] + j12 * cam[8], j11 * cam[5] + j12 * cam[9], j11 * cam[6] + j12 * cam[10]

    # rotation R from the quaternion (normalised; zero = identity)
    qw, qx, qy, qz = np.float64(quats[i, 0]), np.float64(quats[i, 1]), np.float64(quats[i, 2]), np.float64(quats[i, 3])
    qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    if qn > 1e-8:
        iq = 1.0 / qn
        qw, qx, qy, qz = qw * iq, qx * iq, qy * iq, qz * iq
    else:
        qw, qx, qy, qz = 1.0, 0.0, 0.0, 0.0
    r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
    r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
    r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)

    # M = J W R S (2x3), rows m and n; 2D covariance M M^T + 0.3 I, exact determinant
    s0 = min(np.float64(scales[i, 0]), MAX_SCALE)
    s1 = min(np.float64(scales[i, 1]), MAX_SCALE)
    s2 = min(np.float64(scales[i, 2]), MAX_SCALE)
    m0, m1, m2 = (a0 * r00 + a1 * r10 + a2 * r20) * s0, (a0 * r01 + a1 * r11 + a2 * r21) * s1, (a0 * r02 + a1 * r12 + a2 * r22) * s2
    n0, n1, n2 = (b0 * r00 + b1 * r10 + b2 * r20) * s0, (b0 * r01 + b1 * r11 + b2 * r21) * s1, (b0 * r02 + b1 * r12 + b2 * r22) * s2
    mm, nn, mn = m0 * m0 + m1 * m1 + m2 * m2, n0 * n0 + n1 * n1 + n2 * n2, m0 * n0 + m1 * n1 + m2 * n2
    k0, k1, k2 = m1 * n2 - m2 * n1, m2 * n0 - m0 * n2, m0 * n1 - m1 * n0
    det = DILATION**2 + DILATION * (mm + nn) + (k0 * k0 + k1 * k1 + k2 * k2)
    a, c = mm + DILATION, nn + DILATION

    # pixel box of the ellipse q <= min(9, 2 ln(255 o)); pixel centres at (j + 0.5, i + 0.5)
    u = fx * x * iz + cx
    v = fy * y * iz + cy
    ext = SIGMA_EXTENT if o > _OPAC_FULL_EXTENT else math.sqrt(min(max(2 * math.log(o / ALPHA_MIN), 0.0), SIGMA_EXTENT**2))
    rx, ry = ext * math.sqrt(a), ext * math.sqrt(c)
    x0 = max(math.ceil(min(max(u - rx - 0.5, -1.0), width)), 0)
    x1 = min(math.floor(min(max(u + rx - 0.5, -1.0), width)), width - 1)
    y0 = max(math.ceil(min(max(v - ry - 0.5, -1.0), height)), 0)
    y1 = min(math.floor(min(max(v + ry - 0.5, -1.0), height)), height - 1)
    if x0 > x1 or y0 > y1:
        return
    keys[i] = z
    boxes[i, 0], boxes[i, 1], boxes[i, 2], boxes[i, 3] = x0, y0, x1, y1
    idet = 1.0 / det
    red, green, blue = _sh_rgb(sh, i, mx - cam[20], my - cam[21], mz - cam[22], degree)
    rec[i, _U], rec[i, _V] = u, v  # the stores round to rec's dtype; rounding commutes with 2x
    rec[i, _A], rec[i, _B2], rec[i, _C] = c * idet, -2 * mn * idet, a * idet
    rec[i, _O] = opacities[i]
    rec[i, _R], rec[i, _G], rec[i, _BL] = red, green, blue
    rec[i, _Z] = z


@_jit()
def _sh_add(sh, g, k, basis, r, gr, bl):
    return r + basis * sh[g, k, 0], gr + basis * sh[g, k, 1], bl + basis * sh[g, k, 2]


@_jit()
def _sh_rgb(sh, g, dx, dy, dz, degree):
    """max(0, sum_k sh[g, k] Y_k(d) + 0.5) in float64 with the basis of ``sh.sh_basis``."""
    r, gr, bl = _sh_add(sh, g, 0, 0.28209479177387814, 0.0, 0.0, 0.0)
    if degree >= 1:
        n = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        x, y, z = dx / n, dy / n, dz / n
        r, gr, bl = _sh_add(sh, g, 1, -0.4886025119029199 * y, r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 2, 0.4886025119029199 * z, r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 3, -0.4886025119029199 * x, r, gr, bl)
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        r, gr, bl = _sh_add(sh, g, 4, 1.0925484305920792 * xy, r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 5, -1.0925484305920792 * yz, r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 6, 0.31539156525252005 * (2 * zz - xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 7, -1.0925484305920792 * xz, r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 8, 0.5462742152960396 * (xx - yy), r, gr, bl)
    if degree >= 3:
        r, gr, bl = _sh_add(sh, g, 9, -0.5900435899266435 * y * (3 * xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 10, 2.890611442640554 * xy * z, r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 11, -0.4570457994644658 * y * (4 * zz - xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 12, 0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 13, -0.4570457994644658 * x * (4 * zz - xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 14, 1.445305721320277 * z * (xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 15, -0.5900435899266435 * x * (xx - 3 * yy), r, gr, bl)
    if degree >= 4:
        r, gr, bl = _sh_add(sh, g, 16, 2.5033429417967046 * xy * (xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 17, -1.7701307697799304 * yz * (3 * xx - yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 18, 0.9461746957575601 * xy * (7 * zz - 1), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 19, -0.6690465435572892 * yz * (7 * zz - 3), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 20, 0.10578554691520431 * (zz * (35 * zz - 30) + 3), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 21, -0.6690465435572892 * xz * (7 * zz - 3), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 22, 0.47308734787878004 * (xx - yy) * (7 * zz - 1), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 23, -1.7701307697799304 * xz * (xx - 3 * yy), r, gr, bl)
        r, gr, bl = _sh_add(sh, g, 24, 0.6258357354491761 * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)), r, gr, bl)
    return max(r + 0.5, 0.0), max(gr + 0.5, 0.0), max(bl + 0.5, 0.0)


@_jit()
def _argsort_depth(keys, idx):
    """Stable ascending order of the positive float64 ``keys[idx]`` (LSD radix sort, 11-bit
    digits of the IEEE bits, which order like the values for positive numbers)."""
    n = idx.shape[0]
    bits = keys[idx].view(np.uint64)
    order = np.arange(n).astype(np.int32)
    tmp = np.empty(n, np.int32)
    hist = np.zeros(2048, np.int64)
    for shift in range(0, 64, 11):
        hist[:] = 0
        for k in range(n):
            hist[(bits[k] >> np.uint64(shift)) & np.uint64(2047)] += 1
        if hist.max() == n:  # this digit is the same for all keys
            continue
        total = 0
        for d in range(2048):
            cnt = hist[d]
            hist[d] = total
            total += cnt
        for k in range(n):
            o = order[k]
            d = (bits[o] >> np.uint64(shift)) & np.uint64(2047)
            tmp[hist[d]] = o
            hist[d] += 1
        order, tmp = tmp, order
    return idx[order]


@_jit()
def _compact(keys):
    """Indices of the Gaussians that survived projection, ascending."""
    count = 0
    for i in range(keys.shape[0]):
        count += keys[i] < np.inf
    idx = np.empty(count, np.int32)
    count = 0
    for i in range(keys.shape[0]):
        if keys[i] < np.inf:
            idx[count] = i
            count += 1
    return idx


@_jit()
def _compact(keys):
    """Indices of the Gaussians that survived projection, ascending."""
    count = 0
    for i in range(keys.shape[0]):
        count += keys[i] < np.inf
    idx = np.empty(count, np.int32)
    count = 0
    for i in range(keys.shape[0]):
        if keys[i] < np.inf:
            idx[count] = i
            count += 1
    return idx


@_jit()
def _project_serial(means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height, dtype_of):
    """Projected splats in depth order: (M, 10) records and (M, 4) int32 boxes."""
    n = means.shape[0]
    rec, boxes, keys = np.empty((n, _REC), dtype_of.dtype), np.empty((n, 4), np.int32), np.empty(n)
    for i in range(n):
        _project_one(i, means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height, rec, boxes, keys)
    ids = _argsort_depth(keys, _compact(keys))
    return rec[ids], boxes[ids]


@_jit(parallel=True)
def _project_parallel(means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height, dtype_of):
    n = means.shape[0]
    rec, boxes, keys = np.empty((n, _REC), dtype_of.dtype), np.empty((n, 4), np.int32), np.empty(n)
    for i in prange(n):
        _project_one(i, means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height, rec, boxes, keys)
    ids = _argsort_depth(keys, _compact(keys))
    m = ids.shape[0]
    rec_sorted, boxes_sorted = np.empty((m, _REC), rec.dtype), np.empty((m, 4), np.int32)
    for r in prange(m):
        rec_sorted[r] = rec[ids[r]]
        boxes_sorted[r] = boxes[ids[r]]
    return rec_sorted, boxes_sorted


# --------------------------------------------------------------------------- binning
@_jit()
def _bin_chunk(boxes, lo, hi, ntx, counts, ids):
    """For splats lo..hi-1: count them per tile (``ids`` empty) or append them to the tile
    lists at the cursors ``counts`` (``ids`` given)."""
    fill = ids.shape[0] > 0
    for r in range(lo, hi):
        tx0, tx1 = boxes[r, 0] // TILE, boxes[r, 2] // TILE
        for ty in range(boxes[r, 1] // TILE, boxes[r, 3] // TILE + 1):
            for tx in range(tx0, tx1 + 1):
                t = ty * ntx + tx
                if fill:
                    ids[counts[t]] = r
                counts[t] += 1


@_jit()
def _bin_offsets(counts):
    """Turn (chunks, tiles) counts into list cursors; returns the (tiles + 1,) tile starts."""
    nchunks, ntiles = counts.shape
    start = np.empty(ntiles + 1, np.int32)
    total = 0
    for t in range(ntiles):
        start[t] = total
        for c in range(nchunks):
            cnt = counts[c, t]
            counts[c, t] = total
            total += cnt
    start[ntiles] = total
    return start


@_jit()
def _bin_serial(boxes, ntx, nty):
    counts = np.zeros((1, ntx * nty), np.int32)
    _bin_chunk(boxes, 0, boxes.shape[0], ntx, counts[0], np.empty(0, np.int32))
    start = _bin_offsets(counts)
    ids = np.empty(start[-1], np.int32)
    _bin_chunk(boxes, 0, boxes.shape[0], ntx, counts[0], ids)
    return start, ids


@_jit(parallel=True)
def _bin_parallel(boxes, ntx, nty, nchunks):
    """Chunks of consecutive splats are binned independently; chunk c's entries of a tile
    go before chunk c+1's, so every tile list stays in depth order."""
    n = boxes.shape[0]
    counts = np.zeros((nchunks, ntx * nty), np.int32)
    for c in prange(nchunks):
        _bin_chunk(boxes, c * n // nchunks, (c + 1) * n // nchunks, ntx, counts[c], np.empty(0, np.int32))
    start = _bin_offsets(counts)
    ids = np.empty(start[-1], np.int32)
    for c in prange(nchunks):
        _bin_chunk(boxes, c * n // nchunks, (c + 1) * n // nchunks, ntx, counts[c], ids)
    return start, ids


# --------------------------------------------------------------------------- rasterization
@_jit()
def _raster_tile(tile, rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, buf, rgb, depth, alpha):
    """Composite the splats listed for one tile front to back and write its pixels.

    k: constants in the compute dtype: 0.99, 1/255, 1e-4, -0.5, 9, 0, 1, then the Taylor
        coefficients 1/9!, ..., 1/1!, 1 of exp, then 1/8 and -5 (the exponential's range).
    buf: (6, 16, 16) scratch: transmittance, r, g, b, depth, pixel-centre coordinates.
    """
    amax, amin, tmin, mhalf, nine, zero, one = k[0], k[1], k[2], k[3], k[4], k[5], k[6]
    p9, p8, p7, p6, p5, p4, p3, p2, p1, p0 = k[7], k[8], k[9], k[10], k[11], k[12], k[13], k[14], k[15], k[16]
    eighth, lowest = k[17], k[18]
    tx, ty = tile % ntx, tile // ntx
    x_org, y_org = tx * TILE, ty * TILE
    nx, ny = min(TILE, width - x_org), min(TILE, height - y_org)
    trans, acc_r, acc_g, acc_b, acc_d = buf[0], buf[1], buf[2], buf[3], buf[4]
    xs, ys = buf[5, 0], buf[5, 1]
    trans[:] = one
    acc_r[:] = zero
    acc_g[:] = zero
    acc_b[:] = zero
    acc_d[:] = zero
    for i in range(TILE):  # pixel centres, exact in float32
        xs[i] = x_org + i + 0.5
        ys[i] = y_org + i + 0.5
    rowmask = np.zeros(TILE, np.int64)  # live pixels of each tile row, one bit per column
    for ly in range(ny):
        rowmask[ly] = (1 << nx) - 1
    n_live = nx * ny

    for e in range(start[tile], start[tile + 1]):
        r = ids[e]
        lx0, lx1 = max(boxes[r, 0] - x_org, 0), min(boxes[r, 2] - x_org, TILE - 1)
        ly0, ly1 = max(boxes[r, 1] - y_org, 0), min(boxes[r, 3] - y_org, TILE - 1)
        colmask = ((1 << (lx1 + 1)) - 1) & ~((1 << lx0) - 1)
        u, v, ca, cb2, cc, o = rec[r, _U], rec[r, _V], rec[r, _A], rec[r, _B2], rec[r, _C], rec[r, _O]
        cr, cg, cbl, cz = rec[r, _R], rec[r, _G], rec[r, _BL], rec[r, _Z]
        for ly in range(ly0, ly1 + 1):
            live = rowmask[ly] & colmask
            if live == 0:
                continue
            dy = ys[ly] - v
            cq = cc * (dy * dy)
            stopped = 0
            for lx in range(TILE):  # branch-free: one SIMD row
                dx = xs[lx] - u
                q = (ca * (dx * dx) + (cb2 * dx) * dy) + cq
                # exp(-q/2) = exp(y/8)^8 with a Taylor polynomial for exp(y/8), y in [-5, 0]
                y = max(mhalf * q, lowest) * eighth
                p = ((((((((p9 * y + p8) * y + p7) * y + p6) * y + p5) * y + p4) * y + p3) * y + p2) * y + p1) * y + p0
                p = p * p
                p = p * p
                p = p * p
                a = min(o * p, amax)
                t = trans[ly, lx]
                t_next = t * (one - a)
                hit = (((live >> lx) & 1) == 1) & (q <= nine) & (a >= amin)
                take = hit & (t_next >= tmin)
                stop = hit & (t_next < tmin)
                w = a * t if take else zero
                acc_r[ly, lx] += w * cr
                acc_g[ly, lx] += w * cg
                acc_b[ly, lx] += w * cbl
                if want_depth:
                    acc_d[ly, lx] += w * cz
                trans[ly, lx] = t_next if take else t
                stopped |= np.int64(stop) << lx
            if stopped:
                rowmask[ly] &= ~stopped
                for lx in range(TILE):
                    n_live -= (stopped >> lx) & 1
        if n_live == 0:
            break

    for ly in range(ny):
        for lx in range(nx):
            p = (y_org + ly) * width + x_org + lx
            t = trans[ly, lx]
            rgb[p, 0] = acc_r[ly, lx] + t * bg[0]
            rgb[p, 1] = acc_g[ly, lx] + t * bg[1]
            rgb[p, 2] = acc_b[ly, lx] + t * bg[2]
            alpha[p] = one - t
            if want_depth:
                depth[p] = acc_d[ly, lx]


@_jit()
def _raster_serial(rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, buf, rgb, depth, alpha):
    for tile in range(start.shape[0] - 1):
        _raster_tile(tile, rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, buf[0], rgb, depth, alpha)


@_jit(parallel=True)
def _raster_parallel(rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, buf, rgb, depth, alpha):
    """Thread c renders tiles c, c + n, c + 2n, ... (neighbouring tiles cost about the same)."""
    n = buf.shape[0]
    ntiles = start.shape[0] - 1
    for c in prange(n):
        for tile in range(c, ntiles, n):
            _raster_tile(tile, rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, buf[c], rgb, depth, alpha)


# --------------------------------------------------------------------------- entry point
@contextmanager
def _numba_threads(n: int):
    previous = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        yield
    finally:
        numba.set_num_threads(previous)


def _constants(dtype) -> np.ndarray:
    """The constants of ``_raster_tile`` in the compute dtype."""
    taylor = [1.0 / math.factorial(j) for j in range(9, -1, -1)]
    return np.array([ALPHA_MAX, ALPHA_MIN, T_MIN, -0.5, SIGMA_EXTENT**2, 0.0, 1.0, *taylor, 0.125, -5.0], dtype)


def render_fast(
    gaussians: Gaussians,
    camera: Cameras,
    *,
    background: torch.Tensor,
    near: float,
    sh_degree: int | None,
    out_dtype: torch.dtype,
    return_depth: bool,
    threads: int = 1,
    timings: dict[str, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Render one camera (``len(camera) == 1``) on the CPU; the "fast" backend.

    Args:
        threads: CPU threads (capped at ``numba.config.NUMBA_NUM_THREADS``); 1 runs serial code.
        timings: if given, receives the milliseconds of "projection", "binning" and "raster".
        Others: as for every backend (see ``rendering.BACKENDS``).
    Returns:
        rgb (H*W, 3), depth_sum (H*W,) = sum_i w_i z_i or None without ``return_depth``,
        alpha (H*W,), in ``out_dtype`` on the Gaussians' device.
    """
    threads = int(threads)
    if threads < 1:
        raise ValueError(f"fast renderer: threads must be >= 1, got {threads}")
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    carried = sh_degree_from_bases(gaussians.sh.shape[1])
    degree = carried if sh_degree is None else min(int(sh_degree), carried)
    if degree < 0:
        raise ValueError(f"SH degree must be >= 0, got {sh_degree}")
    compute = torch.float64 if out_dtype == torch.float64 else torch.float32
    dtype = np.float64 if compute == torch.float64 else np.float32
    W, H = camera.width, camera.height

    def arr(t: torch.Tensor, dt=compute) -> np.ndarray:
        return t.detach().to("cpu", dt).contiguous().numpy()

    tick = time.perf_counter()
    f64 = torch.float64
    means, quats, scales = arr(gaussians.means), arr(gaussians.quats), arr(gaussians.scales)
    opacities, sh = arr(gaussians.opacities), arr(gaussians.sh)
    # the opacity cull compares in the opacities' own dtype, as project() does
    opac_min = torch.tensor(ALPHA_MIN, dtype=gaussians.opacities.dtype).item()
    w2c = camera.w2c()[0].to(f64)
    fx, fy, cx, cy = (float(v) for v in camera.K[0].to(f64)[[0, 1, 0, 1], [0, 1, 2, 2]])
    fov = FOV_CLAMP - 1  # as in project()
    lims = [(W - cx) / fx + fov * W / fx, cx / fx + fov * W / fx, (H - cy) / fy + fov * H / fy, cy / fy + fov * H / fy]
    cam = np.array([*w2c[:3].reshape(-1).tolist(), fx, fy, cx, cy, *lims, *camera.centers[0].tolist()])
    parallel = threads > 1
    with _numba_threads(threads) if parallel else nullcontext():
        project = _project_parallel if parallel else _project_serial
        rec, boxes = project(means, quats, scales, opacities, sh, degree, cam, float(near), opac_min, W, H, np.empty(0, dtype))
        tock = time.perf_counter()
        ntx, nty = -(-W // TILE), -(-H // TILE)
        start, ids = _bin_parallel(boxes, ntx, nty, threads) if parallel else _bin_serial(boxes, ntx, nty)
        tock2 = time.perf_counter()
        rgb = torch.empty(H * W, 3, dtype=compute)
        alpha = torch.empty(H * W, dtype=compute)
        depth = torch.empty(H * W if return_depth else 0, dtype=compute)
        bg = arr(background)
        buf = np.empty((threads, 6, TILE, TILE), dtype)
        raster = _raster_parallel if parallel else _raster_serial
        raster(rec, boxes, start, ids, W, H, ntx, bg, return_depth, _constants(dtype), buf,
               rgb.numpy(), depth.numpy(), alpha.numpy())
    if timings is not None:
        end = time.perf_counter()
        timings.update(projection=(tock - tick) * 1e3, binning=(tock2 - tock) * 1e3, raster=(end - tock2) * 1e3)
    dev = gaussians.device
    return (
        rgb.to(dev, out_dtype),
        depth.to(dev, out_dtype) if return_depth else None,
        alpha.to(dev, out_dtype),
    )
