"""A brute-force 3DGS renderer for tests: every Gaussian against every pixel, sequential
front-to-back compositing in float64. Written independently of the library's projection
and pair-list code so that agreement between the two means something."""

from __future__ import annotations

import torch


def _quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    n = q.norm(dim=-1, keepdim=True)
    q = torch.where(n > 1e-8, q / n.clamp_min(1e-8), torch.tensor([1.0, 0, 0, 0], dtype=q.dtype))
    w, x, y, z = q.unbind(-1)
    R = torch.empty(q.shape[0], 3, 3, dtype=q.dtype)
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = 1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = 2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)
    return R


def dense_render(means, quats, scales, opacities, colors, K, c2w, width, height, background, near=0.01):
    """Render (3, H, W) rgb, (H, W) expected depth, (H, W) alpha with view-independent
    ``colors`` (N, 3). All inputs are converted to float64."""
    d = torch.float64
    means, quats, scales, opacities, colors = (t.detach().to(d) for t in (means, quats, scales, opacities, colors))
    K, c2w = K.to(d), c2w.to(d)
    R, t = c2w[:3, :3], c2w[:3, 3]
    cam = (means - t) @ R  # world -> camera: R^T (p - t)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    jv, iv = torch.meshgrid(torch.arange(width, dtype=d) + 0.5, torch.arange(height, dtype=d) + 0.5, indexing="xy")
    T = torch.ones(height, width, dtype=d)
    rgb = torch.zeros(3, height, width, dtype=d)
    depth = torch.zeros(height, width, dtype=d)
    done = torch.zeros(height, width, dtype=torch.bool)
    Rg = _quat_to_rotmat(quats)
    for g in torch.argsort(cam[:, 2], stable=True).tolist():
        x, y, z = cam[g]
        if z <= near or opacities[g] < 1 / 255:
            continue
        lx = (1.3 - 1) * 0.5 * width / fx  # 3DGS: 0.3 * tan(half field of view)
        ly = (1.3 - 1) * 0.5 * height / fy
        tx = torch.clamp(x / z, -(cx / fx + lx), (width - cx) / fx + lx)
        ty = torch.clamp(y / z, -(cy / fy + ly), (height - cy) / fy + ly)
        J = torch.tensor([[fx / z, 0, -fx * tx / z], [0, fy / z, -fy * ty / z]], dtype=d)
        S = Rg[g] @ torch.diag(scales[g].clamp(max=1e3) ** 2) @ Rg[g].T
        cov = J @ R.T @ S @ R @ J.T + 0.3 * torch.eye(2, dtype=d)
        inv = torch.linalg.inv(cov)
        du, dv = jv - (fx * x / z + cx), iv - (fy * y / z + cy)
        q = inv[0, 0] * du * du + 2 * inv[0, 1] * du * dv + inv[1, 1] * dv * dv
        alpha = torch.clamp(opacities[g] * torch.exp(-0.5 * q), max=0.99)
        hit = (q <= 9) & (alpha >= 1 / 255) & ~done
        t_next = T * (1 - alpha)
        stop = hit & (t_next < 1e-4)
        done |= stop
        hit &= ~stop
        w = torch.where(hit, alpha * T, torch.zeros_like(T))
        rgb += w * colors[g][:, None, None]
        depth += w * z
        T = torch.where(hit, t_next, T)
    alpha = 1 - T
    rgb += T * torch.as_tensor(background, dtype=d)[:, None, None]
    depth = torch.where(alpha > 0, depth / alpha.clamp_min(1e-10), torch.zeros_like(depth))
    return rgb, depth, alpha
