"""A depth sensor's own depth maps registered to its colour camera.

An RGB-D camera measures depth with its own lens (a RealSense D435: the left infrared imager,
87 x 58 degrees, 15 mm beside the 69 x 42 degree colour imager); a recording that keeps the
raw stream, as LeRobot 0.6 records a RealSense, has depth whose pixel (u, v) is not the
colour image's pixel (u, v), even at the same size. :func:`register_depth` moves every
depth pixel into the colour camera as ``rs2::align`` to colour does: the pixel's footprint
(its two opposite corners, back-projected at its depth, moved by the sensor-to-camera
transform and projected) fills the colour pixels whose centres it covers with its depth
along the colour camera's axis; where footprints overlap the nearest wins; colour pixels
no footprint reaches get 0 (no depth).

The rule runs as one compiled (numba) pass over the depth pixels, in float64, since it runs
once per camera and timestep when a cache is built (its cost: ``benchmarks/depth_registration.py``).
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.cameras import Cameras
from ..core.jit import _jit
from ..core.views import MAX_VIEW_DEPTH

#: colour pixels one depth pixel may fill along each axis (a footprint this wide or wider is
#: cut to it: a surface at a grazing angle, or closer than the sensors' baseline)
MAX_FOOTPRINT = 8


@_jit(inline=True)
def _project(x, y, d, fx, fy, cx, cy, T, Fx, Fy, Cx, Cy):
    """(u, v, z) in the camera of the sensor's pixel position (x, y) at depth d."""
    x, y = (x - cx) / fx * d, (y - cy) / fy * d
    qx = T[0, 0] * x + T[0, 1] * y + T[0, 2] * d + T[0, 3]
    qy = T[1, 0] * x + T[1, 1] * y + T[1, 2] * d + T[1, 3]
    z = T[2, 0] * x + T[2, 1] * y + T[2, 2] * d + T[2, 3]
    return Fx * qx / z + Cx, Fy * qy / z + Cy, z


@_jit()
def _register(depth, sensor_K, to_camera, camera_K, out, max_depth, max_footprint):
    """Fill ``out`` (n, H, W), +inf on entry, with the nearest z of the footprints of
    ``depth`` (n, h, w) pixels; both K (3, 3), to_camera (4, 4), all float64 but depth."""
    n, h, w = depth.shape
    H, W = out.shape[1], out.shape[2]
    fx, fy, cx, cy = sensor_K[0, 0], sensor_K[1, 1], sensor_K[0, 2], sensor_K[1, 2]
    Fx, Fy, Cx, Cy = camera_K[0, 0], camera_K[1, 1], camera_K[0, 2], camera_K[1, 2]
    for i in range(n):
        for r in range(h):
            for c in range(w):
                d = np.float64(depth[i, r, c])
                if not (d > 0.0 and d <= max_depth):
                    continue
                # the footprint's corners (offsets 0 and 1) and centre (0.5), in the camera
                u0, v0, z0 = _project(c, r, d, fx, fy, cx, cy, to_camera, Fx, Fy, Cx, Cy)
                u1, v1, z1 = _project(c + 1.0, r + 1.0, d, fx, fy, cx, cy, to_camera, Fx, Fy, Cx, Cy)
                z = _project(c + 0.5, r + 0.5, d, fx, fy, cx, cy, to_camera, Fx, Fy, Cx, Cy)[2]
                if not (z0 > 0.0 and z1 > 0.0 and z > 0.0):
                    continue  # closer than the sensors' baseline: behind the colour camera
                # colour pixels whose centres (col + 0.5, row + 0.5) the footprint covers
                c0 = np.ceil(min(u0, u1) - 0.5)
                c1 = np.floor(max(u0, u1) - 0.5)
                r0 = np.ceil(min(v0, v1) - 0.5)
                r1 = np.floor(max(v0, v1) - 0.5)
                if not (c1 >= 0.0 and r1 >= 0.0 and c0 < W and r0 < H):
                    continue  # outside the colour image (or not finite)
                c0, r0 = max(c0, 0.0), max(r0, 0.0)
                c1 = min(c1, W - 1.0, c0 + max_footprint - 1.0)
                r1 = min(r1, H - 1.0, r0 + max_footprint - 1.0)
                for row in range(int(r0), int(r1) + 1):
                    for col in range(int(c0), int(c1) + 1):
                        out[i, row, col] = min(out[i, row, col], z)


def register_depth(depth: torch.Tensor, sensor: Cameras, camera: Cameras) -> torch.Tensor:
    """(..., h, w) z-depth in metres of ``sensor`` (one camera of size w x h) as (..., H, W)
    z-depth of ``camera`` (one camera of size W x H; both poses in one world frame), 0 where
    nothing was measured, in ``depth``'s dtype (float32 for integer input) and device.
    Invalid depth (see :func:`.geometry.base.valid_depth`) is skipped.

    Example: the same camera twice gives the depth back
        >>> K = torch.tensor([[10.0, 0, 4], [0, 10, 4], [0, 0, 1]])
        >>> cam = Cameras(K[None], torch.eye(4)[None], 8, 8)
        >>> depth = torch.full((8, 8), 2.0)
        >>> bool((register_depth(depth, cam, cam) == 2.0).all())
        True
    """
    if len(sensor) != 1 or len(camera) != 1:
        raise ValueError(f"register_depth: one sensor and one camera, got {len(sensor)} and {len(camera)}")
    if tuple(depth.shape[-2:]) != (sensor.height, sensor.width):
        raise ValueError(f"register_depth: depth of shape {tuple(depth.shape)} for a {sensor.width}x{sensor.height} "
                         "sensor")  # fmt: skip
    lead, (h, w) = depth.shape[:-2], depth.shape[-2:]
    d = depth.detach().reshape(-1, h, w).to("cpu", torch.float32).contiguous().numpy()
    out = np.full((d.shape[0], camera.height, camera.width), np.inf, dtype=np.float32)
    to_camera = camera.w2c()[0].double() @ sensor.c2w[0].double()
    geometry = [t.detach().to("cpu", torch.float64).contiguous().numpy() for t in (sensor.K[0], to_camera, camera.K[0])]
    _register(d, *geometry, out, MAX_VIEW_DEPTH, MAX_FOOTPRINT)
    out[np.isinf(out)] = 0.0
    dtype = depth.dtype if depth.is_floating_point() else torch.float32
    return torch.from_numpy(out).reshape(*lead, camera.height, camera.width).to(depth.device, dtype)
