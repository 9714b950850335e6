"""The optional "gsplat" backend: :func:`gsplat.rasterization` on CUDA behind ``render``.

gsplat is an optional extra (it needs CUDA to build); without it, or without a CUDA
device, the backend raises ``RuntimeError`` saying which is missing.

Conventions (ours -> gsplat), which match so that no data is reordered:

* cameras: our ``c2w`` is camera-to-world in the OpenCV convention (x right, y down,
  z forward); gsplat's ``viewmats`` are world-to-camera in the same OpenCV convention, so
  ``viewmats = camera.w2c()``; ``Ks`` are the same pixel intrinsics with pixel (row i,
  col j) centred at (j + 0.5, i + 0.5) in both.
* quaternions: w-x-y-z in both. They are normalised here as in our projection (a zero
  quaternion becomes the identity, where gsplat's own normalisation would divide by zero).
* scales: standard deviations along the rotated axes in both (not log-scales); clamped at
  the projection's ``MAX_SCALE`` so that gsplat's float32 covariances stay finite.
* SH: our (N, K, 3) coefficients are gsplat's ``colors`` with ``sh_degree``; both use the
  3DGS real SH basis, view direction = mean - camera centre, and rgb = max(0, SH + 0.5).
* projection: the same 1.3x field-of-view clamp of the Jacobian and the same dilation of
  the 2D covariance (gsplat ``eps2d``: 0.3 px^2 unless ``render`` is given another); the same near-plane cull
  (camera z must exceed ``near``; gsplat keeps z == ``near_plane``, so this backend passes
  the next float32 above ``near``).
* compositing: front-to-back with alpha >= 1/255 and stopping at transmittance 1e-4 in
  both. Differences: gsplat clamps alpha at 0.999 (ours 0.99); gsplat visits a square of
  radius 3 sqrt(lambda_max) around each centre and does not cut at the 3-sigma ellipse,
  whereas ours keeps only pixels with Mahalanobis q <= 9 (and a tighter box for opacity
  below 0.36). The differences touch only pixels where a splat's weight is small or
  alpha saturates, so images agree closely but not bit for bit (docs/rendering.md gives
  the figure on the standard scene). gsplat neither culls centres beyond ``MAX_DEPTH`` (1e32 m) nor clamps
  colours at ``MAX_COLOR`` (1e32), so only scenes beyond those limits differ there. gsplat
  projects in float32: an extremely anisotropic splat (scales 1e3 and 1e-12, the "needle"
  hard case) loses its 2D covariance to cancellation and is dropped, where our float64
  projection draws it.
* depth: ``render_mode="RGB+ED"`` returns the expected depth sum(w z) / alpha; this backend
  multiplies it back by alpha to return ``depth_sum`` as every backend does.
"""

from __future__ import annotations

import numpy as np
import torch

from ..core.cameras import Cameras, rigid_inverse
from ..core.gaussians import Gaussians
from ..core.rotations import normalize_quat
from ..core.sh import sh_degree_from_bases
from .projection import DILATION, MAX_SCALE

_NEEDS = "gsplat backend needs CUDA and the gsplat package: "


def _rasterization():
    """gsplat's ``rasterization``, or RuntimeError naming what is missing."""
    if not torch.cuda.is_available():
        raise RuntimeError(_NEEDS + "no CUDA device is available (torch.cuda.is_available() is False)")
    try:
        from gsplat import rasterization
    except ImportError as e:
        hint = "install the extra: pip install 'gensplat-transforms[gsplat]'"
        raise RuntimeError(_NEEDS + f"gsplat is not importable ({e}); {hint}") from e
    return rasterization


def check_gsplat() -> None:
    """RuntimeError naming what is missing when the gsplat backend cannot run on this machine."""
    _rasterization()


def _just_above(near: float) -> float:
    """gsplat culls z < near_plane in float32; ours culls z <= near: the next float32 above."""
    return float(np.nextafter(np.float32(near), np.float32(np.inf)))


def render_gsplat(
    gaussians: Gaussians,
    camera: Cameras,
    *,
    background: torch.Tensor,
    near: float,
    sh_degree: int | None,
    out_dtype: torch.dtype,
    return_depth: bool,
    dilation: float,
) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
    """Render one camera (``len(camera) == 1``) with gsplat on the default CUDA device.

    Args: as for every backend (see ``render.BACKENDS``).
    Returns:
        rgb (H*W, 3), depth_sum (H*W,) = expected depth * alpha or None without
        ``return_depth``, alpha (H*W,); in ``out_dtype`` on the Gaussians' device.
    """
    rasterization = _rasterization()
    if len(gaussians) == 0:  # nothing to draw (gsplat itself dies on an empty scene: SIGFPE)
        n = camera.height * camera.width
        zeros = torch.zeros(n, dtype=out_dtype, device=gaussians.device)
        return background.to(out_dtype).expand(n, 3).clone(), zeros if return_depth else None, zeros
    dev = torch.device("cuda")
    g = gaussians.to(dev, torch.float32)
    colors, alphas = _rasterize(rasterization, g.means, g.quats, g.scales, g.opacities, g.sh, camera.w2c().to(dev),
                                camera.K.to(dev), camera.width, camera.height, background.to(dev), near, sh_degree,
                                "RGB+ED" if return_depth else "RGB", dilation)  # fmt: skip
    colors, alpha = colors[0].reshape(-1, colors.shape[-1]), alphas[0].reshape(-1)
    depth_sum = colors[:, 3] * alpha if return_depth else None

    def out(t: torch.Tensor) -> torch.Tensor:
        return t.to(gaussians.device, out_dtype)

    return out(colors[:, :3]), None if depth_sum is None else out(depth_sum), out(alpha)


def render_gsplat_batch(
    means: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor, sh: torch.Tensor,
    c2w: torch.Tensor, K: torch.Tensor, width: int, height: int, background: torch.Tensor, near: float = 0.01,
    return_depth: bool = False, dilation: float = DILATION,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """M scenes, each into its own C cameras, in one gsplat call on the tensors' CUDA device.

    Args:
        means (M, N, 3), quats (M, N, 4), scales (M, N, 3), opacities (M, N), sh (M, N, K, 3):
            the Gaussians of each scene (float32; opacity 0 pads a scene: gsplat culls those);
        c2w (M, C, 4, 4), K (M, C, 3, 3): the cameras of each scene, sharing one image size;
        background: (3,) RGB; near, dilation: as for :func:`~gensplat_transforms.rendering.render`
        (opacities already multiplied by its ``saturation``).
    Returns:
        rgb (M, C, 3, H, W), alpha (M, C, 1, H, W) and, with ``return_depth``, the expected
        depth sum(w z) / sum(w) (M, C, 1, H, W) (else None), float32.
    """
    colors, alphas = _rasterize(_rasterization(), means, quats, scales, opacities, sh, rigid_inverse(c2w), K, width,
                                height, background, near, None, "RGB+ED" if return_depth else "RGB", dilation)  # fmt: skip
    colors, alphas = colors.permute(0, 1, 4, 2, 3), alphas.permute(0, 1, 4, 2, 3)
    return colors[:, :, :3], alphas, colors[:, :, 3:] if return_depth else None


def _rasterize(rasterization, means, quats, scales, opacities, sh, w2c, K, width, height, background, near,
               sh_degree, render_mode, dilation) -> tuple[torch.Tensor, torch.Tensor]:
    """gsplat's rasterization with this backend's conventions (module docstring); leading
    dimensions of the Gaussians (..., N) and cameras (..., C) batch scenes. Returns colors
    (..., C, H, W, D) and alphas (..., C, H, W, 1)."""
    carried = sh_degree_from_bases(sh.shape[-2])
    degree = carried if sh_degree is None else min(int(sh_degree), carried)
    f32 = torch.float32
    colors, alphas, _ = rasterization(
        means.to(f32), normalize_quat(quats.to(f32)), scales.to(f32).clamp(max=MAX_SCALE), opacities.to(f32),
        sh.to(f32), viewmats=w2c.to(f32), Ks=K.to(f32), width=width, height=height, near_plane=_just_above(near),
        eps2d=dilation, sh_degree=degree,
        # packed=False: gsplat 1.5.3 rejects per-camera backgrounds in packed mode (shape assert)
        backgrounds=background.to(f32).expand(*w2c.shape[:-2], 3), packed=False, render_mode=render_mode,
    )  # fmt: skip
    return colors, alphas
