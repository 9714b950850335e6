"""Fast CPU inference backend ("fast"): projection and tile rasterization compiled with numba.

Same rules and outputs as :mod:`.projection` + :mod:`.reference` (see projection.py), not
differentiable. One frame runs in three compiled stages:

1. projection, in float64 like ``project()``, in blocks of 128 Gaussians that stay in
   cache from input to output: EWA conic, depth and opacity-aware pixel box of every
   Gaussian (branch-free, SIMD over the block), culling (near plane, opacity, off-image);
   then, for the block's visible splats only, the colour from SH up to the requested degree
   and one float32 record each, written in index order; their front-to-back order by a
   stable radix sort on the bits of the depths rounded to float32, runs of equal roundings
   finished in float64;
2. binning: each splat is listed in the 16x16 tiles its box touches, in depth order (a
   counting sort: the tiles' list lengths are counted in memory order, which reads the boxes
   sequentially, then the lists filled in depth order); one-tile splats, most of them, take a
   branch without loops;
3. rasterization, tile by tile with the Gaussian-outer loop: each splat visits the rows of
   its box inside the tile, and evaluates a whole 16-pixel tile row at once, or an 8-pixel
   window of it when its box is at most 8 pixels wide there (about 60 % of rows in the
   standard scene), branch-free and in float32 lanes only, so the compiler can use SIMD of
   the machine's full width (the exponential is a polynomial for that reason). A pixel
   stops (its live flag drops to 0) at the splat that would take its transmittance below
   1e-4; every 16 splats the tile's live pixels are counted, rows without any are skipped
   and a tile without any stops; tiles without splats only get the background. Depth is
   accumulated only when asked for.

fastmath is off (IEEE arithmetic, like the reference) except fused multiply-adds inside
the exponential's polynomial.

Numbers: the projection runs in float64 like ``project()``, everything after it in float32
whatever the input dtype (float64 Gaussians are rounded to float32 first, after
``render`` has brought them into float32's range with ``projection.precondition``; the
outputs are returned in the API's dtype). Per (splat, pixel) pair the arithmetic follows the
reference's float32 operations one by one except the exponential (a polynomial, relative
error below 2e-6) and the transmittance (a running product instead of a float64 sum of
logarithms), so images agree with the reference to about 1e-6.

Threads: ``threads=1`` (the default, one dataloader worker = one thread) runs serial
compiled code that never starts numba's thread pool, so it is safe in forked workers;
``threads=n > 1`` runs the parallel version on ``min(n, numba.config.NUMBA_NUM_THREADS)``
threads and restores numba's thread count afterwards. The image does not depend on the
thread count. numba's OpenMP layer shares the OpenMP runtime with torch and changes its
thread count, which is restored after each call. Its idle threads busy-wait between
parallel regions, which on a small, busy machine takes the CPU from the serial parts
(docs/rendering.md, "threads and compiled code"); start such processes with
``OMP_WAIT_POLICY=PASSIVE`` in the environment (read when torch loads OpenMP) or
``NUMBA_THREADING_LAYER=workqueue``.

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

from ..core.cameras import Cameras
from ..core.gaussians import Gaussians
from ..core.jit import _jit
from ..core.sh import sh_degree_from_bases
from .projection import (
    ALPHA_MAX,
    ALPHA_MIN,
    MAX_COLOR,
    MAX_DEPTH,
    MAX_SCALE,
    SIGMA_EXTENT,
    T_MIN,
    fov_limits,
)

_TILE_BITS = 4
TILE = 1 << _TILE_BITS  # tile side in pixels (16): one tile row is one 16-lane vector
# fields of a splat's float32 record: centre u, v; conic A, 2B, C; opacity; colour; depth
_U, _V, _A, _B2, _C, _O, _R, _G, _BL, _Z = range(10)
_REC = 10
_BLOCK = 128  # Gaussians per block of the projection (see _project_range)
# rows of a projection block: inputs (means 0-2, quaternions 3-6, scales 7-9), opacity,
# geometry (8, see _geometry), box (4), visibility, colour (3)
_B_OPACITY, _B_GEOM, _B_BOX, _B_VISIBLE, _B_COLOR, _B_ROWS = 10, 11, 19, 23, 24, 27
# above this opacity the box extent is the full 3 sigma: 2 ln(255 o) > 9 for o > 0.353
_OPAC_FULL_EXTENT = 0.36


# --------------------------------------------------------------------------- projection
@_jit(inline=True)
def _pixel_box(u, v, rx, ry, width, height):
    """Inclusive pixel bounds (x0, y0, x1, y1) of the pixel centres (j + 0.5, i + 0.5)
    within rx, ry of (u, v), clipped to the image (empty when x0 > x1 or y0 > y1)."""
    x0 = max(math.ceil(min(max(u - rx - 0.5, -1.0), width)), 0)
    x1 = min(math.floor(min(max(u + rx - 0.5, -1.0), width)), width - 1)
    y0 = max(math.ceil(min(max(v - ry - 0.5, -1.0), height)), 0)
    y1 = min(math.floor(min(max(v + ry - 0.5, -1.0), height)), height - 1)
    return x0, y0, x1, y1


@_jit(inline=True)
def _geometry(lo, hi, soa, opacities, cam, near, opac_min, width, height, geom, boxes, visible):
    """EWA projection of Gaussians lo..hi-1 with projection.py's rules, in float64 (up to
    rounding: some divisions are products with a reciprocal). The loop is branch-free, so it
    compiles to SIMD code where the compiler can tell that the arrays do not overlap (see
    ``_project_range``); the box uses the full 3-sigma extent (see ``_shrink_box``).
    Inlined, with the loop inside: as a per-Gaussian call in a loop it stays scalar.

    soa: (10, N) rows: means (3), quaternions w-x-y-z (4), scales (3).
    cam: (24,) float64: world-to-camera rows (12), fx, fy, cx, cy, the field-of-view clamp
        limits of x/z (+, -) and y/z (+, -), camera centre (3), the dilation (px^2).
    geom: (8, N) float64 out: u, v, conic A, 2B, C, depth, sqrt(cov_xx), sqrt(cov_yy).
    boxes: (4, N) out (whole numbers).  visible: (N,) out (1 or 0).
    """
    w00, w01, w02, w03, w10, w11, w12, w13 = cam[0], cam[1], cam[2], cam[3], cam[4], cam[5], cam[6], cam[7]
    w20, w21, w22, w23 = cam[8], cam[9], cam[10], cam[11]
    fx, fy, cx, cy = cam[12], cam[13], cam[14], cam[15]
    lim_xp, lim_xn, lim_yp, lim_yn = cam[16], cam[17], cam[18], cam[19]
    dil = cam[23]
    for i in range(lo, hi):
        mx, my, mz = np.float64(soa[0, i]), np.float64(soa[1, i]), np.float64(soa[2, i])
        x = w00 * mx + w01 * my + w02 * mz + w03
        y = w10 * mx + w11 * my + w12 * mz + w13
        z = w20 * mx + w21 * my + w22 * mz + w23
        iz = 1.0 / z
        # rows of J W (2x3): J = [[fx/z, 0, -fx tx/z], [0, fy/z, -fy ty/z]] with the
        # field-of-view clamp on tx = x/z, ty = y/z; W = camera rotation
        tx = min(max(x * iz, -lim_xn), lim_xp)
        ty = min(max(y * iz, -lim_yn), lim_yp)
        j00, j02, j11, j12 = fx * iz, -fx * tx * iz, fy * iz, -fy * ty * iz
        a0, a1, a2 = j00 * w00 + j02 * w20, j00 * w01 + j02 * w21, j00 * w02 + j02 * w22
        b0, b1, b2 = j11 * w10 + j12 * w20, j11 * w11 + j12 * w21, j11 * w12 + j12 * w22

        # rotation R from the quaternion (normalised; zero = identity)
        qw, qx = np.float64(soa[3, i]), np.float64(soa[4, i])
        qy, qz = np.float64(soa[5, i]), np.float64(soa[6, i])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        unit = qn > 1e-8
        iq = 1.0 / qn
        qw = qw * iq if unit else 1.0
        qx = qx * iq if unit else 0.0
        qy = qy * iq if unit else 0.0
        qz = qz * iq if unit else 0.0
        r00, r01, r02 = 1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)
        r10, r11, r12 = 2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)
        r20, r21, r22 = 2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)

        # M = J W R S (2x3) with rows m, n; 2D covariance M M^T + dil I, exact determinant
        s0 = min(np.float64(soa[7, i]), MAX_SCALE)
        s1 = min(np.float64(soa[8, i]), MAX_SCALE)
        s2 = min(np.float64(soa[9, i]), MAX_SCALE)
        m0 = (a0 * r00 + a1 * r10 + a2 * r20) * s0
        m1 = (a0 * r01 + a1 * r11 + a2 * r21) * s1
        m2 = (a0 * r02 + a1 * r12 + a2 * r22) * s2
        n0 = (b0 * r00 + b1 * r10 + b2 * r20) * s0
        n1 = (b0 * r01 + b1 * r11 + b2 * r21) * s1
        n2 = (b0 * r02 + b1 * r12 + b2 * r22) * s2
        mm, nn, mn = m0 * m0 + m1 * m1 + m2 * m2, n0 * n0 + n1 * n1 + n2 * n2, m0 * n0 + m1 * n1 + m2 * n2
        k0, k1, k2 = m1 * n2 - m2 * n1, m2 * n0 - m0 * n2, m0 * n1 - m1 * n0
        det = dil * dil + dil * (mm + nn) + (k0 * k0 + k1 * k1 + k2 * k2)
        idet = 1.0 / det
        sa, sc = math.sqrt(mm + dil), math.sqrt(nn + dil)

        u = fx * x * iz + cx
        v = fy * y * iz + cy
        x0, y0, x1, y1 = _pixel_box(u, v, SIGMA_EXTENT * sa, SIGMA_EXTENT * sc, width, height)
        geom[0, i], geom[1, i], geom[5, i], geom[6, i], geom[7, i] = u, v, z, sa, sc
        geom[2, i], geom[3, i], geom[4, i] = (nn + dil) * idet, -2 * mn * idet, (mm + dil) * idet
        boxes[0, i], boxes[1, i], boxes[2, i], boxes[3, i] = x0, y0, x1, y1
        visible[i] = (z > near) & (z < MAX_DEPTH) & (opacities[i] >= opac_min) & (x0 <= x1) & (y0 <= y1)


@_jit(inline=True)
def _shrink_box(j, blk, width, height):
    """For visible lane j of a block (see ``_project_range``) with opacity <= 0.36, shrink its
    box to the opacity-aware extent sqrt(2 ln(255 o)) < 3 sigma, as project() does (it may
    leave the image)."""
    o = blk[_B_OPACITY, j]
    if o <= _OPAC_FULL_EXTENT:
        ext = math.sqrt(min(max(2 * math.log(o / ALPHA_MIN), 0.0), SIGMA_EXTENT**2))
        rx, ry = ext * blk[_B_GEOM + 6, j], ext * blk[_B_GEOM + 7, j]
        x0, y0, x1, y1 = _pixel_box(blk[_B_GEOM, j], blk[_B_GEOM + 1, j], rx, ry, width, height)
        blk[_B_BOX, j], blk[_B_BOX + 1, j], blk[_B_BOX + 2, j], blk[_B_BOX + 3, j] = x0, y0, x1, y1
        blk[_B_VISIBLE, j] = (x0 <= x1) & (y0 <= y1)


@_jit(inline=True)
def _sh_dot(sh, g, k0, basis):
    """sum_j basis[j] * sh[g, k0 + j] for one SH band (basis: a tuple), per channel."""
    r, gr, bl = 0.0, 0.0, 0.0
    for j in range(len(basis)):
        r += basis[j] * sh[g, k0 + j, 0]
        gr += basis[j] * sh[g, k0 + j, 1]
        bl += basis[j] * sh[g, k0 + j, 2]
    return r, gr, bl


@_jit(inline=True)
def _sh_rgb(sh, g, dx, dy, dz, degree):
    """sum_k sh[g, k] Y_k(d) + 0.5 clamped to [0, MAX_COLOR], in float64, for d = (dx, dy, dz)
    normalised, with the basis of ``sh.sh_basis`` up to ``degree``; returns (r, g, b)."""
    r, gr, bl = _sh_dot(sh, g, 0, (0.28209479177387814,))
    if degree >= 1:
        n = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        x, y, z = dx / n, dy / n, dz / n
        band = _sh_dot(sh, g, 1, (-0.4886025119029199 * y, 0.4886025119029199 * z, -0.4886025119029199 * x))
        r, gr, bl = r + band[0], gr + band[1], bl + band[2]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        band = _sh_dot(sh, g, 4, (
            1.0925484305920792 * xy,
            -1.0925484305920792 * yz,
            0.31539156525252005 * (2 * zz - xx - yy),
            -1.0925484305920792 * xz,
            0.5462742152960396 * (xx - yy),
        ))  # fmt: skip
        r, gr, bl = r + band[0], gr + band[1], bl + band[2]
    if degree >= 3:
        band = _sh_dot(sh, g, 9, (
            -0.5900435899266435 * y * (3 * xx - yy),
            2.890611442640554 * xy * z,
            -0.4570457994644658 * y * (4 * zz - xx - yy),
            0.3731763325901154 * z * (2 * zz - 3 * xx - 3 * yy),
            -0.4570457994644658 * x * (4 * zz - xx - yy),
            1.445305721320277 * z * (xx - yy),
            -0.5900435899266435 * x * (xx - 3 * yy),
        ))  # fmt: skip
        r, gr, bl = r + band[0], gr + band[1], bl + band[2]
    if degree >= 4:
        band = _sh_dot(sh, g, 16, (
            2.5033429417967046 * xy * (xx - yy),
            -1.7701307697799304 * yz * (3 * xx - yy),
            0.9461746957575601 * xy * (7 * zz - 1),
            -0.6690465435572892 * yz * (7 * zz - 3),
            0.10578554691520431 * (zz * (35 * zz - 30) + 3),
            -0.6690465435572892 * xz * (7 * zz - 3),
            0.47308734787878004 * (xx - yy) * (7 * zz - 1),
            -1.7701307697799304 * xz * (xx - 3 * yy),
            0.6258357354491761 * (xx * (xx - 3 * yy) - yy * (3 * xx - yy)),
        ))  # fmt: skip
        r, gr, bl = r + band[0], gr + band[1], bl + band[2]
    return (min(max(r + 0.5, 0.0), MAX_COLOR), min(max(gr + 0.5, 0.0), MAX_COLOR),
            min(max(bl + 0.5, 0.0), MAX_COLOR))  # fmt: skip


@_jit(inline=True)
def _pack(j, blk, rec, boxes, keys, m):
    """Record m from lane j of a block (see ``_project_range``).

    rec: (M, 10) float32 out, rounded from float64 as project(out_dtype=float32) rounds
    (rounding commutes with 2B = 2 * B). boxes: (M, 4) int32 out. keys: (M,) float64 out:
    depths.
    """
    g, c = _B_GEOM, _B_COLOR
    rec[m, _U], rec[m, _V], rec[m, _Z] = blk[g, j], blk[g + 1, j], blk[g + 5, j]
    rec[m, _A], rec[m, _B2], rec[m, _C] = blk[g + 2, j], blk[g + 3, j], blk[g + 4, j]
    rec[m, _O] = blk[_B_OPACITY, j]
    rec[m, _R], rec[m, _G], rec[m, _BL] = blk[c, j], blk[c + 1, j], blk[c + 2, j]
    for k in range(4):
        boxes[m, k] = np.int32(blk[_B_BOX + k, j])
    keys[m] = blk[g + 5, j]


@_jit()
def _argsort_depth(keys):
    """Stable ascending order of positive float64 keys (M,), as ``np.argsort(kind="stable")``.

    LSD radix sort on 11-bit digits of the keys rounded to float32, whose IEEE bits order
    like the values: 3 passes instead of 6 on the float64 bits. The three digit histograms
    are counted in one read of the bits, and each pass moves the bits along with the indices,
    so that no pass reads them in a random order. Rounding is monotone, so only keys with
    equal roundings can be out of order; each such run (rare) is finished by a stable sort of
    its float64 keys.
    """
    n = keys.shape[0]
    bits = keys.astype(np.float32).view(np.uint32)
    hist = np.zeros((3, 2048), np.int64)
    for k in range(n):
        b = bits[k]
        hist[0, b & np.uint32(2047)] += 1
        hist[1, (b >> np.uint32(11)) & np.uint32(2047)] += 1
        hist[2, b >> np.uint32(22)] += 1
    order, tmp = np.empty(n, np.int32), np.empty(n, np.int32)
    for k in range(n):
        order[k] = k
    tmp_bits = np.empty(n, np.uint32)
    for p in range(3):
        total, single = 0, False
        for d in range(2048):
            cnt = hist[p, d]
            single |= cnt == n  # the same digit for every key: nothing to do
            hist[p, d] = total
            total += cnt
        if single:
            continue
        shift = np.uint32(11 * p)
        for k in range(n):
            b = bits[k]
            d = (b >> shift) & np.uint32(2047)
            at = hist[p, d]
            tmp[at], tmp_bits[at] = order[k], b
            hist[p, d] = at + 1
        order, tmp = tmp, order
        bits, tmp_bits = tmp_bits, bits
    i = 0
    while i < n:  # bits are sorted now
        j = i + 1
        while j < n and bits[j] == bits[i]:
            j += 1
        if j - i > 1:  # a run in ascending index order: a stable sort keeps ties in it
            run = order[i:j].copy()
            order[i:j] = run[np.argsort(keys[run], kind="mergesort")]
        i = j
    return order


@_jit()
def _project_range(lo, hi, means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height,
                   rec, boxes, keys):  # fmt: skip
    """The visible splats among Gaussians lo..hi-1 (inputs as in ``Gaussians``, ``cam`` as in
    ``_geometry``), in index order: their records, boxes and depths (see ``_pack``) written
    to rows lo, lo + 1, ...; returns how many.

    In blocks of ``_BLOCK`` Gaussians held in one float64 array of constant shape (inputs,
    opacity, geometry, box, visibility, colour: rows ``_B_*``), so that the compiler sees that
    nothing in ``_geometry``'s loop overlaps, and vectorises it. The per-splat rest of a
    block runs over lists of its lanes made by branch-free compaction: with the box shrink
    inside one plain loop, the compiler computes its logarithm for every Gaussian.
    """
    blk = np.zeros((_B_ROWS, _BLOCK))
    lanes = np.empty(_BLOCK, np.int64)
    m = lo
    for b0 in range(lo, hi, _BLOCK):
        nb = min(_BLOCK, hi - b0)
        for j in range(nb):
            i = b0 + j
            blk[0, j], blk[1, j], blk[2, j] = means[i, 0], means[i, 1], means[i, 2]
            blk[3, j], blk[4, j], blk[5, j], blk[6, j] = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
            blk[7, j], blk[8, j], blk[9, j] = scales[i, 0], scales[i, 1], scales[i, 2]
            blk[_B_OPACITY, j] = opacities[i]
        # lanes past nb hold stale inputs and are never read
        _geometry(0, _BLOCK, blk[:_B_OPACITY], blk[_B_OPACITY], cam, near, opac_min, width, height,
                  blk[_B_GEOM:_B_BOX], blk[_B_BOX:_B_VISIBLE], blk[_B_VISIBLE])  # fmt: skip
        low = 0
        for j in range(nb):
            lanes[low] = j
            low += (blk[_B_VISIBLE, j] != 0.0) & (blk[_B_OPACITY, j] <= _OPAC_FULL_EXTENT)
        for k in range(low):
            _shrink_box(lanes[k], blk, width, height)
        nv = 0
        for j in range(nb):
            lanes[nv] = j
            nv += blk[_B_VISIBLE, j] != 0.0
        # colours in a loop of their own: inside the record loop, the branches on the SH
        # degree made it 2-3x slower
        for k in range(nv):
            j = lanes[k]
            dx, dy, dz = blk[0, j] - cam[20], blk[1, j] - cam[21], blk[2, j] - cam[22]
            c = _B_COLOR
            blk[c, j], blk[c + 1, j], blk[c + 2, j] = _sh_rgb(sh, b0 + j, dx, dy, dz, degree)
        for k in range(nv):
            _pack(lanes[k], blk, rec, boxes, keys, m + k)
        m += nv
    return m - lo


@_jit()
def _project_serial(means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height):
    """The M visible splats: float32 records (M, 10), int32 pixel boxes (M, 4), and their
    order front to back (M,). Inputs as in ``Gaussians`` (float32), ``cam`` as in
    ``_geometry``."""
    n = means.shape[0]
    rec, boxes, keys = np.empty((n, _REC), np.float32), np.empty((n, 4), np.int32), np.empty(n)
    m = _project_range(0, n, means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height,
                       rec, boxes, keys)  # fmt: skip
    return rec[:m], boxes[:m], _argsort_depth(keys[:m])


@_jit(parallel=True)
def _project_parallel(
    means, quats, scales, opacities, sh, degree, cam, near, opac_min, width, height, nchunks
):  # fmt: skip
    """``_project_serial`` in chunks of Gaussians; each chunk's splats are then moved down
    to follow the previous chunk's."""
    n = means.shape[0]
    rec, boxes, keys = np.empty((n, _REC), np.float32), np.empty((n, 4), np.int32), np.empty(n)
    counts = np.empty(nchunks, np.int64)
    for c in prange(nchunks):
        counts[c] = _project_range(c * n // nchunks, (c + 1) * n // nchunks, means, quats, scales, opacities, sh,
                                   degree, cam, near, opac_min, width, height, rec, boxes, keys)  # fmt: skip
    m = 0
    for c in range(nchunks):
        src = c * n // nchunks
        for k in range(counts[c]):  # m <= src: a forward copy never overwrites what it reads
            rec[m] = rec[src + k]
            boxes[m] = boxes[src + k]
            keys[m] = keys[src + k]
            m += 1
    return rec[:m], boxes[:m], _argsort_depth(keys[:m])


# --------------------------------------------------------------------------- binning
@_jit(inline=True)
def _tile_range(boxes, i):
    """Tiles (tx0, ty0, tx1, ty1), inclusive, that splat i's box touches: a box lies in the
    image (coordinates >= 0), so a shift is the floor division."""
    return (boxes[i, 0] >> _TILE_BITS, boxes[i, 1] >> _TILE_BITS, boxes[i, 2] >> _TILE_BITS,
            boxes[i, 3] >> _TILE_BITS)  # fmt: skip


@_jit()
def _bin_count(boxes, order, lo, hi, ntx, counts):
    """Add to ``counts`` (tiles,) the tiles of splats order[lo..hi-1], or of splats lo..hi-1
    when ``order`` is None (the counts do not depend on the order, and memory order is the
    fastest to read)."""
    for k in range(lo, hi):
        i = k if order is None else order[k]
        tx0, ty0, tx1, ty1 = _tile_range(boxes, i)
        if tx0 == tx1 and ty0 == ty1:  # most splats: one tile
            counts[ty0 * ntx + tx0] += 1
        else:
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    counts[ty * ntx + tx] += 1


@_jit()
def _bin_fill(boxes, order, lo, hi, ntx, cursors, ids):
    """Append the splats order[lo..hi-1] to the lists of their tiles at ``cursors`` (tiles,),
    advancing them."""
    for k in range(lo, hi):
        i = order[k]
        tx0, ty0, tx1, ty1 = _tile_range(boxes, i)
        if tx0 == tx1 and ty0 == ty1:
            t = ty0 * ntx + tx0
            ids[cursors[t]] = i
            cursors[t] += 1
        else:
            for ty in range(ty0, ty1 + 1):
                for tx in range(tx0, tx1 + 1):
                    t = ty * ntx + tx
                    ids[cursors[t]] = i
                    cursors[t] += 1


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
def _bin_serial(order, boxes, ntx, nty):
    """Tile lists in depth order: splats ids[start[t]:start[t+1]] touch tile t."""
    n = order.shape[0]
    counts = np.zeros((1, ntx * nty), np.int32)
    _bin_count(boxes, None, 0, n, ntx, counts[0])
    start = _bin_offsets(counts)
    ids = np.empty(start[-1], np.int32)
    _bin_fill(boxes, order, 0, n, ntx, counts[0], ids)
    return start, ids


@_jit(parallel=True)
def _bin_parallel(order, boxes, ntx, nty, nchunks):
    """Chunks of consecutive splats in depth order are binned independently; chunk c's
    entries of a tile go before chunk c+1's, so every tile list stays in depth order."""
    n = order.shape[0]
    counts = np.zeros((nchunks, ntx * nty), np.int32)
    for c in prange(nchunks):
        _bin_count(boxes, order, c * n // nchunks, (c + 1) * n // nchunks, ntx, counts[c])
    start = _bin_offsets(counts)
    ids = np.empty(start[-1], np.int32)
    for c in prange(nchunks):
        _bin_fill(boxes, order, c * n // nchunks, (c + 1) * n // nchunks, ntx, counts[c], ids)
    return start, ids


# --------------------------------------------------------------------------- rasterization
def _exp_coefficients(degree: int = 6, lo: float = -0.625) -> list[float]:
    """Coefficients, highest power first, of the Chebyshev interpolant of exp on [lo, 0]:
    near-minimax, so degree 6 is as accurate in float32 as the degree-9 Taylor polynomial."""
    interpolant = np.polynomial.Chebyshev.interpolate(np.exp, degree, domain=[lo, 0.0])
    return interpolant.convert(kind=np.polynomial.Polynomial).coef[::-1].tolist()


#: float32 constants of ``_raster_tile``: alpha cap and threshold, transmittance floor, -1/2,
#: the footprint limit q <= 9, 0, 1, then 1/8 and -5 (argument scale and floor of the
#: exponential, whose value matters only for q <= 9) and the 7 coefficients of ``_exp8``.
_CONSTANTS = np.array(
    [ALPHA_MAX, ALPHA_MIN, T_MIN, -0.5, SIGMA_EXTENT**2, 0.0, 1.0, 0.125, -5.0] + _exp_coefficients(),
    np.float32,
)


@_jit(fastmath={"contract"})
def _exp8(y, c):
    """exp(8 y) for y in [-5/8, 0]: a degree-6 polynomial approximation of exp(y) with
    coefficients c (``_exp_coefficients``), raised to the 8th power: 9 operations, relative
    error < 2e-6 in float32 (tested). Plain arithmetic, so that the row loop inlining it
    compiles to SIMD code; fused multiply-adds only here."""
    p = c[0]
    for j in range(1, 7):
        p = p * y + c[j]
    p = p * p
    p = p * p
    return p * p


# planes of a tile's state (see ``_raster_tile``): transmittance, colour, depth, live flag
_T, _RED, _GREEN, _BLUE, _DEPTH, _LIVE = range(6)
_RECOUNT = 16  # a tile's live pixels are counted after every _RECOUNT splats


@_jit(inline=True)
def _blend_row(state, ly, x_start, lanes, splat, want_depth, consts, poly):
    """Composite one splat into the pixels x_start .. x_start + lanes - 1 of tile row ly:
    branch-free, one SIMD vector of ``lanes`` (a constant at each call site). Every lane
    value is float32 and every condition a float select: integer lanes are 64-bit in numba
    (a bit mask per row made the AVX2 code 4 lanes wide) and boolean vectors are packed and
    unpacked around each logical operation.

    state: (6, TILE, TILE) float32 planes ``_T`` .. ``_LIVE`` of the tile, the only array the
    loop touches (with constant offsets, so the compiler needs no run-time alias checks,
    without which it would not vectorise an 8-lane loop); a pixel composites while its
    ``_LIVE`` entry is 1 and is set to 0 at the splat that would take its transmittance below
    T_MIN. splat: (x0, u, conic A, 2B, opacity, r, g, b, depth, dy, C dy^2, first and last
    column of its box in the tile) for this row, x0 being the tile's first pixel centre and
    dy the row centre minus v; consts: the first 9 ``_CONSTANTS``.
    """
    amax, amin, tmin, mhalf, nine, zero, one, eighth, lowest = consts
    x0, u, ca, cb2, o, cr, cg, cbl, cz, dy, cq, first, last = splat
    for j in range(lanes):
        lx = x_start + j
        col = np.float32(x_start) + np.float32(j)
        dx = (col + x0) - u  # the pixel centre is exact in float32
        q = (ca * (dx * dx) + (cb2 * dx) * dy) + cq
        a = min(o * _exp8(max(mhalf * q, lowest) * eighth, poly), amax)
        t = state[_T, ly, lx]
        live = state[_LIVE, ly, lx]
        # alpha of a pixel the splat composites, else 0: float selects only (no boolean
        # vectors, which AVX2 code packs and unpacks)
        a = a * live
        a = a if q <= nine else zero
        a = a if col >= first else zero
        a = a if col <= last else zero
        a = a if a >= amin else zero
        t_next = t * (one - a)  # t where a = 0
        keep = t_next >= tmin  # else the pixel stops here, before this splat
        w = a * t if keep else zero
        state[_RED, ly, lx] += w * cr
        state[_GREEN, ly, lx] += w * cg
        state[_BLUE, ly, lx] += w * cbl
        if want_depth:
            state[_DEPTH, ly, lx] += w * cz
        state[_T, ly, lx] = t_next if keep else t
        state[_LIVE, ly, lx] = live if keep else zero


@_jit()
def _raster_tile(tile, rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, rgb, depth, alpha):
    """Composite the splats listed for one tile front to back and write its pixels.

    rec: (M, 10) float32 splat records; boxes: (M, 4) their pixel boxes; start, ids: tile
    lists from binning (ids index rec); bg: (3,) background; k: ``_CONSTANTS``.
    rgb (3, H*W), depth (H*W,) (when want_depth) and alpha (H*W,): outputs, written for
    this tile's pixels only.
    """
    consts = (k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], k[8])  # values, not memory
    poly = (k[9], k[10], k[11], k[12], k[13], k[14], k[15])
    zero, one = k[5], k[6]
    tx, ty = tile % ntx, tile // ntx
    x_org, y_org = tx * TILE, ty * TILE
    nx, ny = min(TILE, width - x_org), min(TILE, height - y_org)
    # tile state (planes _T .. _LIVE); allocated here with constant shapes so the compiler
    # sees that the planes do not overlap (no run-time alias checks in the row loop)
    state = np.zeros((6, TILE, TILE), rec.dtype)
    state[_T] = one
    state[_LIVE, :ny, :nx] = one
    x0, y0 = np.float32(x_org + 0.5), np.float32(y_org + 0.5)  # first pixel centre
    row_live = np.zeros(TILE, np.int64)  # live pixels of each tile row at the last count
    row_live[:ny] = nx

    for e in range(start[tile], start[tile + 1]):
        r = ids[e]
        lx0, lx1 = max(boxes[r, 0] - x_org, 0), min(boxes[r, 2] - x_org, TILE - 1)
        ly0, ly1 = max(boxes[r, 1] - y_org, 0), min(boxes[r, 3] - y_org, TILE - 1)
        u, v, ca, cb2, cc, o = rec[r, _U], rec[r, _V], rec[r, _A], rec[r, _B2], rec[r, _C], rec[r, _O]
        cr, cg, cbl, cz = rec[r, _R], rec[r, _G], rec[r, _BL], rec[r, _Z]
        first, last = np.float32(lx0), np.float32(lx1)
        # a box at most 8 columns wide within the tile: an 8-lane window (half the work)
        narrow = lx1 - lx0 < 8
        x_start = min(lx0, 8) if narrow else 0
        for ly in range(ly0, ly1 + 1):
            if row_live[ly] == 0:
                continue
            dy = (np.float32(ly) + y0) - v
            cq = cc * (dy * dy)
            splat = (x0, u, ca, cb2, o, cr, cg, cbl, cz, dy, cq, first, last)
            if narrow:
                _blend_row(state, ly, x_start, 8, splat, want_depth, consts, poly)
            else:
                _blend_row(state, ly, 0, TILE, splat, want_depth, consts, poly)
        if (e - start[tile]) % _RECOUNT == _RECOUNT - 1:  # skip dead rows, stop a dead tile
            n_live = 0
            for ly in range(ny):
                live = 0
                for lx in range(TILE):
                    live += state[_LIVE, ly, lx] > zero
                row_live[ly] = live
                n_live += live
            if n_live == 0:
                break

    for ly in range(ny):
        for lx in range(nx):
            p = (y_org + ly) * width + x_org + lx
            t = state[_T, ly, lx]
            rgb[0, p] = state[_RED, ly, lx] + t * bg[0]
            rgb[1, p] = state[_GREEN, ly, lx] + t * bg[1]
            rgb[2, p] = state[_BLUE, ly, lx] + t * bg[2]
            alpha[p] = one - t
            if want_depth:
                depth[p] = state[_DEPTH, ly, lx]


@_jit()
def _raster_serial(rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, rgb, depth, alpha):
    for tile in range(start.shape[0] - 1):
        _raster_tile(tile, rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, rgb, depth, alpha)


@_jit(parallel=True)
def _raster_parallel(
    rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, rgb, depth, alpha, nchunks
):  # fmt: skip
    """Chunk c renders tiles c, c + n, c + 2n, ... (neighbouring tiles cost about the same)."""
    ntiles = start.shape[0] - 1
    for c in prange(nchunks):
        for tile in range(c, ntiles, nchunks):
            _raster_tile(
                tile, rec, boxes, start, ids, width, height, ntx, bg, want_depth, k, rgb, depth, alpha
            )  # fmt: skip


# --------------------------------------------------------------------------- entry point
@contextmanager
def _numba_threads(n: int):
    """Run numba's parallel code on n threads, then restore numba's and torch's thread
    counts (numba's OpenMP layer can share torch's OpenMP runtime and change torch's)."""
    previous_torch = torch.get_num_threads()  # first: numba's first call may change it
    previous = numba.get_num_threads()
    numba.set_num_threads(n)
    try:
        yield
    finally:
        numba.set_num_threads(previous)
        torch.set_num_threads(previous_torch)


def render_fast(
    gaussians: Gaussians,
    camera: Cameras,
    *,
    background: torch.Tensor,
    near: float,
    sh_degree: int | None,
    out_dtype: torch.dtype,
    return_depth: bool,
    dilation: float,
    threads: int = 1,
    timings: dict[str, float] | None = None,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Render one camera (``len(camera) == 1``) on the CPU: the "fast" backend.

    Args:
        threads: CPU threads (capped at ``numba.config.NUMBA_NUM_THREADS``); 1 runs serial code.
        timings: if given, receives the milliseconds of "projection", "binning" and "raster".
        Others: as for every backend (see ``render.BACKENDS``).
    Returns:
        rgb (H*W, 3) (the transpose of a contiguous (3, H*W), so that ``render``'s (3, H, W)
        planes are a view of it), depth_sum (H*W,) = sum_i w_i z_i or None without ``return_depth``,
        alpha (H*W,); in ``out_dtype`` on the Gaussians' device.
    """
    threads = int(threads)
    if threads < 1:
        raise ValueError(f"fast renderer: threads must be >= 1, got {threads}")
    threads = min(threads, numba.config.NUMBA_NUM_THREADS)
    carried = sh_degree_from_bases(gaussians.sh.shape[1])
    degree = carried if sh_degree is None else min(int(sh_degree), carried)
    if degree < 0:
        raise ValueError(f"SH degree must be >= 0, got {sh_degree}")
    W, H = camera.width, camera.height
    ntx, nty = -(-W // TILE), -(-H // TILE)

    def f32(t: torch.Tensor) -> np.ndarray:
        return t.detach().to("cpu", torch.float32).contiguous().numpy()

    tick = time.perf_counter()
    g = gaussians
    # the opacity cull compares in the opacities' own dtype, as project() does
    opac_min = torch.tensor(ALPHA_MIN, dtype=g.opacities.dtype).item()
    w2c = camera.w2c()[0].to(torch.float64)
    fx, fy, cx, cy = camera.K[0].to(torch.float64)[[0, 1, 0, 1], [0, 1, 2, 2]].tolist()
    lims = fov_limits(W, H, fx, fy, cx, cy)  # the clamp of project()
    cam = np.array([*w2c[:3].reshape(-1).tolist(), fx, fy, cx, cy, *lims, *camera.centers[0].tolist(), dilation])
    rgb = torch.empty(3, H * W)
    alpha = torch.empty(H * W)
    depth = torch.empty(H * W if return_depth else 0)
    project_args = (f32(g.means), f32(g.quats), f32(g.scales), f32(g.opacities), f32(g.sh), degree, cam,
                    float(near), opac_min, W, H)  # fmt: skip
    with _numba_threads(threads) if threads > 1 else nullcontext():
        if threads > 1:
            rec, boxes, order = _project_parallel(*project_args, threads)
        else:
            rec, boxes, order = _project_serial(*project_args)
        tock = time.perf_counter()
        if threads > 1:
            start, ids = _bin_parallel(order, boxes, ntx, nty, threads)
        else:
            start, ids = _bin_serial(order, boxes, ntx, nty)
        tock2 = time.perf_counter()
        raster_args = (rec, boxes, start, ids, W, H, ntx, f32(background), return_depth, _CONSTANTS,
                       rgb.numpy(), depth.numpy(), alpha.numpy())  # fmt: skip
        _raster_parallel(*raster_args, threads) if threads > 1 else _raster_serial(*raster_args)
    if timings is not None:
        end = time.perf_counter()
        ms = {"projection": tock - tick, "binning": tock2 - tock, "raster": end - tock2}
        timings.update({name: 1e3 * seconds for name, seconds in ms.items()})
    dev = g.device
    depth_sum = depth.to(dev, out_dtype) if return_depth else None
    return rgb.T.to(dev, out_dtype), depth_sum, alpha.to(dev, out_dtype)
