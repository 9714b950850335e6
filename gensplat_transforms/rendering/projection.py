"""EWA projection of 3D Gaussians to screen-space splats, shared by every CPU backend.

Rules (reference 3DGS / gsplat): cull Gaussians whose centre is not beyond the near plane
or whose opacity is below 1/255; clamp the Jacobian's x/z, y/z to 1.3x the field of view;
add 0.3 px^2 to the 2D covariance diagonal. Two more keep every float32 stage finite: cull
Gaussians whose centre lies beyond ``MAX_DEPTH``; clamp colours to [0, ``MAX_COLOR``]. The
footprint is the 3-sigma ellipse (Mahalanobis q <= 9); a pixel receives a splat when it
lies inside that ellipse and alpha = min(0.99, o exp(-q/2)) >= 1/255. Backends visit the
tight pixel box of that region.

The projection runs in float64 (cheap: O(N)) so that huge, tiny and very anisotropic
Gaussians keep an exact, positive determinant: with M = J W R S (2x3),
det(M M^T + 0.3 I) = 0.09 + 0.3 tr(M M^T) + |m_1 x m_2|^2 (Cauchy-Binet) has no
cancellation, so no splat is lost or made NaN by round-off.

``render`` passes the Gaussians through :func:`precondition` once, before any backend, so
that backends computing in float32 see the values the float64 reference sees.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..core.cameras import Cameras
from ..core.gaussians import Gaussians
from ..core.rotations import normalize_quat, quat_to_rotmat
from ..core.sh import eval_sh

ALPHA_MIN = 1.0 / 255.0
ALPHA_MAX = 0.99
T_MIN = 1e-4
DILATION = 0.3
SIGMA_EXTENT = 3.0
FOV_CLAMP = 1.3
MAX_SCALE = 1e3  # metres; larger scales are clamped (covers any image anyway)
MAX_DEPTH = 1e32  # metres; farther centres are culled, so float32 depths and their sums stay finite
MAX_COLOR = 1e32  # colours are clamped to [0, MAX_COLOR], so float32 colour sums stay finite
F32_MAX = torch.finfo(torch.float32).max


def precondition(gaussians: Gaussians) -> Gaussians:
    """The Gaussians as every backend renders them: float64 tensors brought into float32's
    finite range (means, scales and SH clamped to +-F32_MAX; quaternions normalised in
    float64, so any finite magnitude is an orientation), so that a backend computing in
    float32 sees what the float64 reference sees. Other dtypes already lie in that range
    and are kept as they are. Differentiable; O(N) work only for float64 tensors."""
    t = gaussians.tensors()
    if all(v.dtype != torch.float64 for v in t.values()):
        return gaussians

    def fit(v: torch.Tensor) -> torch.Tensor:
        return v.clamp(-F32_MAX, F32_MAX) if v.dtype == torch.float64 else v

    quats = normalize_quat(t["quats"]) if t["quats"].dtype == torch.float64 else t["quats"]
    return Gaussians(means=fit(t["means"]), quats=quats, scales=fit(t["scales"]),
                     opacities=t["opacities"], sh=fit(t["sh"]), validate=False)  # fmt: skip


@dataclass
class Projected:
    """M visible splats, sorted front to back (by camera-space z).

    Attributes:
        ids: (M,) indices into the input Gaussians.
        means2d: (M, 2) pixel coordinates of the centres.
        conics: (M, 3) inverse 2D covariance (A, B, C): q = A dx^2 + 2 B dx dy + C dy^2.
        depths: (M,) camera-space z.
        opacities: (M,).
        colors: (M, 3) view-dependent RGB.
        boxes: (M, 4) inclusive pixel bounds (x0, y0, x1, y1) of the 3-sigma ellipse,
            clipped to the image.
    """

    ids: torch.Tensor
    means2d: torch.Tensor
    conics: torch.Tensor
    depths: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    boxes: torch.Tensor

    def __len__(self) -> int:
        return self.ids.shape[0]


def fov_limits(W: int, H: int, fx, fy, cx, cy) -> tuple:
    """Limits (+x, -x, +y, -y) of x/z and y/z where the projection's Jacobian is taken: the
    image edge plus (FOV_CLAMP - 1) * tan(half field of view), as in 3DGS and gsplat."""
    mx, my = (FOV_CLAMP - 1) * 0.5 * W / fx, (FOV_CLAMP - 1) * 0.5 * H / fy
    return (W - cx) / fx + mx, cx / fx + mx, (H - cy) / fy + my, cy / fy + my


def project(
    gaussians: Gaussians,
    camera: Cameras,
    near: float = 0.01,
    sh_degree: int | None = None,
    out_dtype: torch.dtype = torch.float32,
    dilation: float = DILATION,
) -> Projected:
    """Project Gaussians into one camera (``len(camera) == 1``); differentiable w.r.t. the
    Gaussians and ``camera.c2w``. Returns only splats that can touch the image. ``dilation``
    (px^2) replaces the 0.3 added to the 2D covariance diagonal."""
    f64 = torch.float64
    W, H = camera.width, camera.height
    K = camera.K[0].to(f64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    w2c = camera.w2c()[0].to(f64)
    Rwc, twc = w2c[:3, :3], w2c[:3, 3]

    means = gaussians.means.to(f64)
    z_all = means @ Rwc[2] + twc[2]
    keep = (z_all > near) & (z_all < MAX_DEPTH) & (gaussians.opacities >= ALPHA_MIN)
    idx = keep.nonzero().squeeze(1)
    cam = means[idx] @ Rwc.T + twc
    x, y, z = cam.unbind(-1)

    # Jacobian of the perspective map with 3DGS's field-of-view clamp.
    lim_xp, lim_xn, lim_yp, lim_yn = fov_limits(W, H, fx, fy, cx, cy)
    tx = torch.minimum(torch.maximum(x / z, -lim_xn), lim_xp)
    ty = torch.minimum(torch.maximum(y / z, -lim_yn), lim_yp)
    zero = torch.zeros_like(z)
    J = torch.stack(
        [torch.stack([fx / z, zero, -fx * tx / z], -1), torch.stack([zero, fy / z, -fy * ty / z], -1)], -2
    )  # (M, 2, 3)
    scales = gaussians.scales[idx].to(f64).clamp(max=MAX_SCALE)
    M = J @ Rwc @ quat_to_rotmat(gaussians.quats[idx].to(f64)) * scales[:, None, :]  # (M, 2, 3)
    m1, m2 = M[:, 0], M[:, 1]
    a = (m1 * m1).sum(-1) + dilation
    b = (m1 * m2).sum(-1)
    c = (m2 * m2).sum(-1) + dilation
    det = dilation**2 + dilation * ((m1 * m1).sum(-1) + (m2 * m2).sum(-1))
    det = det + torch.linalg.cross(m1, m2).square().sum(-1)
    conics = torch.stack([c / det, -b / det, a / det], -1)

    u = fx * x / z + cx
    v = fy * y / z + cy
    # Box of the ellipse q <= min(9, 2 ln(255 o)): beyond it alpha < 1/255 or q > 9, so
    # these pixels can never receive this splat (opacity-aware, exact culling).
    opac = gaussians.opacities[idx].to(f64).detach()
    ext = (2 * torch.log(opac / ALPHA_MIN)).clamp(0, SIGMA_EXTENT**2).sqrt()
    # Pixel (row i, col j) has its centre at (j + 0.5, i + 0.5).
    rx, ry = ext * a.sqrt(), ext * c.sqrt()
    x0 = torch.ceil((u - rx - 0.5).clamp(-1, W)).long().clamp_min(0)
    x1 = torch.floor((u + rx - 0.5).clamp(-1, W)).long().clamp_max(W - 1)
    y0 = torch.ceil((v - ry - 0.5).clamp(-1, H)).long().clamp_min(0)
    y1 = torch.floor((v + ry - 0.5).clamp(-1, H)).long().clamp_max(H - 1)
    on_image = (x0 <= x1) & (y0 <= y1)

    sel = on_image.nonzero().squeeze(1)
    sel = sel[torch.argsort(z[sel].detach(), stable=True)]
    ids = idx[sel]
    dirs = means[ids] - camera.centers[0].to(f64)
    colors = eval_sh(gaussians.sh[ids].to(f64), dirs, sh_degree).clamp(max=MAX_COLOR)
    boxes = torch.stack([x0, y0, x1, y1], -1)[sel]
    return Projected(
        ids=ids,
        means2d=torch.stack([u, v], -1)[sel].to(out_dtype),
        conics=conics[sel].to(out_dtype),
        depths=z[sel].to(out_dtype),
        opacities=gaussians.opacities[ids].to(out_dtype),
        colors=colors.to(out_dtype),
        boxes=boxes,
    )
