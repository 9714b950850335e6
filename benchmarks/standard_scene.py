"""The standard benchmark scene: a synthetic tabletop seen by three cameras, back-projected
to one pixel-aligned Gaussian per source pixel (about 150k at 224x224).

Geometry (world z up, metres): a textured table top (z = 0) with four shaded boxes on it,
inside a room (floor z = -0.75, walls at +-1.5 m, ceiling z = 2) so that every source ray
hits a surface. Each source pixel becomes a Gaussian at its surface point, flattened along
the surface normal, with tangential standard deviations close to the pixel footprint
(depth / f) and slight random anisotropy; opacity ~0.9; SH degree 3 with the texture in the
DC term and small random higher-order coefficients. The target camera is source view 0
rotated 20 deg about the world y axis through the pivot of views 0 and 1.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from gensplat_transforms import Cameras, Gaussians, look_at, pivot_point
from gensplat_transforms.cameras import focal_from_fov
from gensplat_transforms.perturbation import perturb_pose
from gensplat_transforms.rotations import rotmat_to_quat
from gensplat_transforms.sh import num_sh_bases, rgb_to_sh_dc

# (min corner, max corner, RGB) of the boxes standing on the table
_BOXES = [
    ((-0.30, -0.15, 0.0), (-0.18, -0.03, 0.12), (0.80, 0.20, 0.15)),
    ((0.05, -0.20, 0.0), (0.13, -0.12, 0.20), (0.15, 0.45, 0.85)),
    ((0.15, 0.05, 0.0), (0.33, 0.17, 0.07), (0.20, 0.70, 0.25)),
    ((-0.10, 0.10, 0.0), (-0.02, 0.18, 0.05), (0.90, 0.80, 0.20)),
]
_TABLE = ((-0.5, -0.35), (0.5, 0.35))
_ROOM = ((-1.5, -1.5, -0.75), (1.5, 1.5, 2.0))
_LIGHT = torch.tensor([0.3, -0.4, 0.87], dtype=torch.float64)


@dataclass
class StandardScene:
    """Attributes:
    gaussians: N Gaussians (float32, SH degree 3).
    sources: (3,) source cameras the Gaussians were made from.
    target: (1,) camera to render, source 0 rotated 20 deg about the pivot.
    pivot: (3,) rotation centre.
    """

    gaussians: Gaussians
    sources: Cameras
    target: Cameras
    pivot: torch.Tensor


def _box_hits(o: torch.Tensor, d: torch.Tensor, lo, hi, inside: bool):
    """Ray/axis-aligned box intersection (slab method) for rays o + t d, (R, 3) each.

    Returns the entry (or, with ``inside``, exit) distance (R,), inf on a miss, and the
    face normal (R, 3) pointing towards the ray origin."""
    lo = torch.tensor(lo, dtype=o.dtype)
    hi = torch.tensor(hi, dtype=o.dtype)
    inv = 1.0 / torch.where(d.abs() < 1e-12, torch.full_like(d, 1e-12), d)
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    tnear, tfar = torch.minimum(t0, t1), torch.maximum(t0, t1)
    if inside:
        t, axis = tfar.min(-1)
    else:
        t, axis = tnear.max(-1)
        t = torch.where((t <= tfar.min(-1).values) & (t > 0), t, torch.full_like(t, math.inf))
    normal = torch.zeros_like(d)
    normal.scatter_(1, axis[:, None], -torch.sign(d.gather(1, axis[:, None])))
    return t, normal


def _checker(u: torch.Tensor, v: torch.Tensor, period: float) -> torch.Tensor:
    return ((torch.floor(u / period) + torch.floor(v / period)) % 2).to(u.dtype)


def _raycast(cam: Cameras) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Surface point, normal, colour (each (H*W, 3)) and camera depth (H*W,) per pixel."""
    uv = cam.pixel_centers()
    K, c2w = cam.K[0], cam.c2w[0]
    rays_cam = torch.stack(
        [(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1], torch.ones(len(uv), dtype=uv.dtype)], -1
    )
    d = rays_cam @ c2w[:3, :3].T  # unit camera z, so t is the camera depth
    o = c2w[:3, 3].expand_as(d)

    t, normal = _box_hits(o, d, *_ROOM, inside=True)
    color = torch.empty_like(d)
    p = o + t[:, None] * d
    floor = normal[:, 2] > 0.5
    color[:] = 0.55 + 0.1 * p[:, 2:3]  # walls and ceiling: vertical gradient
    color[floor] = (0.25 + 0.35 * _checker(p[floor, 0], p[floor, 1], 0.25))[:, None] * torch.tensor(
        [1.0, 0.95, 0.85], dtype=d.dtype
    )
    kind = torch.zeros(len(d), dtype=torch.long)  # 0 room, 1 table, 2.. boxes

    # table top: the plane z = 0 inside its rectangle, seen from above
    tt = -o[:, 2] / torch.where(d[:, 2].abs() < 1e-12, torch.full_like(d[:, 2], -1e-12), d[:, 2])
    pt = o + tt[:, None] * d
    (x0, y0), (x1, y1) = _TABLE
    hit = (tt > 0) & (tt < t) & (pt[:, 0] >= x0) & (pt[:, 0] <= x1) & (pt[:, 1] >= y0) & (pt[:, 1] <= y1)
    hit &= d[:, 2] < 0
    t = torch.where(hit, tt, t)
    normal[hit] = torch.tensor([0.0, 0.0, 1.0], dtype=d.dtype)
    kind[hit] = 1
    for b, (lo, hi, rgb) in enumerate(_BOXES):
        tb, nb = _box_hits(o, d, lo, hi, inside=False)
        hit = tb < t
        t = torch.where(hit, tb, t)
        normal[hit] = nb[hit]
        kind[hit] = 2 + b

    p = o + t[:, None] * d
    table = kind == 1
    wood = 0.5 + 0.5 * torch.sin(60 * p[table, 0] + 8 * torch.sin(9 * p[table, 1]))
    check = _checker(p[table, 0], p[table, 1], 0.05)
    color[table] = torch.stack([0.45 + 0.2 * wood, 0.3 + 0.12 * wood, 0.15 + 0.05 * wood], -1) * (
        0.75 + 0.25 * check
    )[:, None]
    for b, (_, _, rgb) in enumerate(_BOXES):
        sel = kind == 2 + b
        shade = 0.35 + 0.65 * (normal[sel] @ _LIGHT).clamp_min(0)
        stripes = 0.85 + 0.15 * torch.sign(torch.sin(80 * (p[sel, 0] + p[sel, 1] + p[sel, 2])))
        color[sel] = torch.tensor(rgb, dtype=d.dtype) * (shade * stripes)[:, None]
    return p, normal, color.clamp(0.02, 0.98), t


def _frames_from_normals(normal: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """(R, 3, 3) rotations whose third column is ``normal``, spun by ``angle`` about it."""
    helper = torch.where(
        normal[:, 2:3].abs() < 0.9,
        torch.tensor([0.0, 0.0, 1.0], dtype=normal.dtype),
        torch.tensor([1.0, 0.0, 0.0], dtype=normal.dtype),
    )
    t1 = torch.linalg.cross(helper, normal)
    t1 = t1 / t1.norm(dim=-1, keepdim=True)
    t2 = torch.linalg.cross(normal, t1)
    c, s = torch.cos(angle)[:, None], torch.sin(angle)[:, None]
    return torch.stack([c * t1 + s * t2, -s * t1 + c * t2, normal], -1)


def standard_scene(size: int = 224, seed: int = 0, footprint: float = 1.7) -> StandardScene:
    """Build the standard scene.

    Args:
        size: source and target image side in pixels (224 in the benchmarks).
        seed: randomness of anisotropy, orientation, opacity and SH.
        footprint: tangential standard deviation in units of the pixel footprint depth / f.
    """
    gen = torch.Generator().manual_seed(seed)
    f = focal_from_fov(60.0, size)
    centre = torch.tensor([0.0, 0.0, 0.05], dtype=torch.float64)
    eyes = []
    for azimuth, elevation, radius in ((-90.0, 45.0, 0.9), (-50.0, 40.0, 0.95), (-130.0, 50.0, 0.85)):
        a, e = math.radians(azimuth), math.radians(elevation)
        eyes.append(centre + radius * torch.tensor([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]))
    c2w = torch.stack([look_at(eye, centre) for eye in eyes])
    sources = Cameras.from_intrinsics(f, f, size / 2, size / 2, c2w, size, size)

    parts = [_raycast(sources[i]) for i in range(len(sources))]
    p, normal, color, depth = (torch.cat(x) for x in zip(*parts, strict=True))
    n = p.shape[0]
    u = lambda *shape: torch.rand(*shape, generator=gen, dtype=torch.float64)  # noqa: E731
    s = footprint * depth / f
    scales = torch.stack([s * (0.85 + 0.3 * u(n)), s * (0.85 + 0.3 * u(n)), 0.1 * s], -1)
    quats = rotmat_to_quat(_frames_from_normals(normal, 2 * math.pi * u(n)))
    sh = 0.03 * torch.randn(n, num_sh_bases(3), 3, generator=gen, dtype=torch.float64)
    sh[:, 0] = rgb_to_sh_dc(color)
    gaussians = Gaussians(
        means=p.float(), quats=quats.float(), scales=scales.float(), opacities=(0.85 + 0.1 * u(n)).float(), sh=sh.float()
    )
    pivot = pivot_point(c2w[0], c2w[1])
    target = sources[0].with_c2w(perturb_pose(c2w[0], pivot, "y", 20.0, 0.0)[None])
    return StandardScene(gaussians=gaussians, sources=sources, target=target, pivot=pivot)
