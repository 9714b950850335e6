"""The render stage: Gaussians into cameras, and the rendered views into an item's images.

Here: :func:`render`, one scene into its cameras, one entry point for several backends
(:mod:`.reference`, differentiable PyTorch over :mod:`.projection`; :mod:`.fast`, the compiled
CPU renderer; :mod:`.gsplat_backend`), and :func:`render_size`, the size the augmented views
are rendered at. Beside it: :mod:`.scenes` (``render_scenes``: B scenes x C cameras, the one
way the transform renders views, in a worker and for a whole batch; holes filled with
:mod:`.holes`), :mod:`.output` (the views moved and sized like an item's images and depth
maps), :mod:`.batched` (``render_batch``: a collated batch at once, ``render_in="batch"``),
:mod:`.warp` (forward warping, the baseline of the fidelity benchmarks) and :mod:`.preview`
(preview images). Imports the stages below it; the transform's settings only as a type.
"""

from __future__ import annotations

import importlib.util
import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ..core.cameras import Cameras
from ..core.gaussians import Gaussians
from .fast import render_fast
from .gsplat_backend import render_gsplat
from .projection import DILATION, Projected, precondition, project
from .reference import rasterize_reference

__all__ = ["BACKENDS", "Projected", "RenderOutput", "auto_backend", "covered", "project", "render", "render_size"]


@dataclass
class RenderOutput:
    """Images for B cameras.

    Attributes:
        rgb: (B, 3, H, W) colour including the background.
        depth: (B, 1, H, W) expected depth sum(w z) / sum(w); 0 where nothing was hit.
        alpha: (B, 1, H, W) accumulated opacity in [0, 1].

    Example:
        >>> out = RenderOutput(rgb=torch.zeros(2, 3, 8, 8))  # what :func:`render` returns
        >>> out.rgb.shape[0], out.depth is None
        (2, True)
    """

    rgb: torch.Tensor
    depth: torch.Tensor | None = None
    alpha: torch.Tensor | None = None


def _render_reference(gaussians: Gaussians, camera: Cameras, *, background: torch.Tensor, near: float,
                      sh_degree: int | None, out_dtype: torch.dtype, return_depth: bool, dilation: float,
                      max_pairs: int = 1 << 22) -> tuple:
    proj = project(gaussians, camera, near=near, sh_degree=sh_degree, out_dtype=out_dtype, dilation=dilation)
    return rasterize_reference(proj, camera.width, camera.height, background, max_pairs=max_pairs)


#: Backend registry. Each entry is called for one camera as
#: ``fn(gaussians, camera, *, background, near, sh_degree, out_dtype, return_depth, dilation, **options)``
#: and returns ``(rgb (H*W, 3), depth_sum (H*W,) or None, alpha (H*W,))`` where depth_sum is
#: sum_i w_i z_i (it may be None when ``return_depth`` is False).
BACKENDS: dict[str, Callable] = {"reference": _render_reference, "fast": render_fast, "gsplat": render_gsplat}


def auto_backend(gaussians: Gaussians, cameras: Cameras, background: object = None) -> str:
    """The backend ``render(backend="auto")`` uses: "reference" (differentiable) when gradients
    are being recorded and any input tensor requires grad; else "gsplat" for Gaussians on a
    CUDA device with gsplat installed; else "fast" (the compiled CPU renderer).

    Example:
        >>> g = Gaussians(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.05),
        ...               torch.ones(1), torch.ones(1, 1, 3))
        >>> camera = Cameras.from_intrinsics(20.0, 20.0, 8.0, 8.0, torch.eye(4), 16, 16)
        >>> learnt = Gaussians(g.means.clone().requires_grad_(), g.quats, g.scales, g.opacities, g.sh)
        >>> auto_backend(g, camera), auto_backend(learnt, camera)
        ('fast', 'reference')
    """
    tensors = [*gaussians.tensors().values(), cameras.K, cameras.c2w, background]
    if torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad for t in tensors):
        return "reference"
    if gaussians.device.type == "cuda" and importlib.util.find_spec("gsplat") is not None:
        return "gsplat"
    return "fast"


def _saturation(saturation: float | torch.Tensor, gaussians: Gaussians) -> float | torch.Tensor | None:
    """``render``'s saturation checked: a number, or (N,) values in the Gaussians' dtype and
    device; None where it is 1 (nothing to scale)."""
    if isinstance(saturation, torch.Tensor) and saturation.ndim > 0:
        if saturation.shape != (len(gaussians),):
            raise ValueError(f"render: saturation per Gaussian must have shape ({len(gaussians)},), "
                             f"got {tuple(saturation.shape)}")  # fmt: skip
        if not saturation.numel():
            return None
        low, high = (float(v) for v in torch.aminmax(saturation.float()))  # one pass; NaN propagates
        if not (math.isfinite(high) and low >= 1):
            raise ValueError("render: saturation must be finite and >= 1 for every Gaussian")
        return saturation.to(gaussians.opacities) if high > 1 else None
    saturation = float(saturation)
    if not (math.isfinite(saturation) and saturation >= 1):
        raise ValueError(f"render: saturation must be a finite number >= 1, got {saturation}")
    return saturation if saturation != 1 else None


def render_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """(width, height) of the views rendered for ``width x height`` images at ``scale``
    (``GenSplatConfig.render_scale``), at least one pixel each.

    Example:
        >>> render_size(640, 480, 0.35)
        (224, 168)
    """
    return max(1, round(width * scale)), max(1, round(height * scale))


def render(
    gaussians: Gaussians,
    cameras: Cameras,
    *,
    background: tuple[float, float, float] | torch.Tensor = (0.0, 0.0, 0.0),
    near: float = 0.01,
    sh_degree: int | None = None,
    backend: str = "auto",
    return_depth: bool = True,
    return_alpha: bool = True,
    dilation: float = DILATION,
    saturation: float | torch.Tensor = 1.0,
    cover: float = 1.0,
    recheck: bool = True,
    **options,
) -> RenderOutput:
    """Render Gaussians from each camera with EWA splatting and front-to-back compositing.

    Args:
        gaussians: the scene (any float dtype; half precision is computed in float32);
            checked in full on every call (``Gaussians.check(force=True)``: writes through
            ``.data`` or a NumPy view are caught too; its cost: docs/numerical_stability.md;
            see ``recheck``), then passed through ``projection.precondition``
            (float64 values beyond float32's range are clamped, float64 quaternions
            normalised) for every backend.
        cameras: B cameras (OpenCV convention) sharing one image size.
        background: RGB added where the splats leave transmittance.
        near: splats whose centre is not beyond this camera-space z are culled.
        sh_degree: evaluate colour only up to this SH degree (default: all carried).
        backend: "auto" (see :func:`auto_backend`: the differentiable reference when an input
            requires grad, gsplat for CUDA Gaussians when installed, else fast) or one of
            ``BACKENDS``: "reference" is differentiable pure PyTorch; "fast" the compiled CPU
            renderer; "gsplat" needs CUDA and the gsplat package.
        return_depth, return_alpha: skip these outputs when False.
        dilation: px^2 added to every splat's 2D covariance (anti-aliasing; 0.3 as in 3DGS and
            gsplat, with which learnt Gaussians are trained); > 0.
        saturation: each splat's alpha is min(0.99, saturation * opacity * exp(-q/2)): above 1,
            flat-topped splats that cover their core fully and fall off within a fraction of
            their size (pixel-aligned RGB-D discs, see ``geometry.rgbd``); >= 1, one
            number or one per Gaussian (N,).
        cover: a pixel whose alpha reaches ``cover`` counts as covered: its colour is the
            splats' own, divided by alpha as depth is, and its alpha 1 (:func:`covered`; the
            cracks between small discs seen from a moved camera); 1 leaves every pixel as
            composited; in (0, 1].
        recheck: False trusts a check the Gaussians passed while torch saw no write to their
            tensors (``Gaussians.check()``), for Gaussians the caller has just built (the
            dataset transform's); writes through ``.data`` or NumPy since then go unseen.
        options: settings of the backend used (reference: ``max_pairs`` per chunk; fast:
            ``threads``).
    Returns:
        RenderOutput with (B, C, H, W) images, float32 (float64 for float64 inputs).

    Example: one Gaussian at the origin, seen from 1 m away
        >>> from gensplat_transforms import look_at
        >>> g = Gaussians(torch.zeros(1, 3), torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.05),
        ...               torch.ones(1), torch.ones(1, 1, 3))
        >>> camera = Cameras.from_intrinsics(20.0, 20.0, 8.0, 8.0, look_at((0, -1, 0), (0, 0, 0)), 16, 16)
        >>> out = render(g, camera)  # backend "auto": "fast" here
        >>> out.rgb.shape, round(float(out.depth[0, 0, 8, 8]), 3)
        (torch.Size([1, 3, 16, 16]), 1.0)
    """
    if backend == "auto":
        backend = auto_backend(gaussians, cameras, background)
    if backend not in BACKENDS:
        raise ValueError(f"unknown render backend {backend!r}; available: 'auto', {sorted(BACKENDS)}")
    gaussians = precondition(gaussians.check(force=recheck))
    if not torch.isfinite(torch.as_tensor(near)) or near <= 0:
        raise ValueError(f"render: near must be a positive finite number, got {near}")
    if not (math.isfinite(dilation) and dilation > 0):
        raise ValueError(f"render: dilation must be a positive finite number of px^2, got {dilation}")
    cover = check_cover(cover)
    saturation = _saturation(saturation, gaussians)
    if saturation is not None:  # opacities above 1 exist only here, for the backends' alpha
        gaussians = Gaussians(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities * saturation,
                              gaussians.sh, validate=False).mark_checked()  # fmt: skip
    out_dtype = torch.float64 if gaussians.dtype == torch.float64 else torch.float32
    bg = torch.as_tensor(background, dtype=out_dtype, device=gaussians.device).reshape(3)
    if not torch.isfinite(bg).all():
        raise ValueError(f"render: background must be finite, got {background}")
    fn = BACKENDS[backend]
    H, W = cameras.height, cameras.width
    rgbs, depths, alphas = [], [], []
    for i in range(len(cameras)):
        rgb, depth_sum, alpha = fn(
            gaussians, cameras[i], background=bg, near=near, sh_degree=sh_degree,
            out_dtype=out_dtype, return_depth=return_depth, dilation=float(dilation), **options,
        )
        rgbs.append(rgb.T.reshape(3, H, W))
        if return_depth:
            depth = torch.where(alpha > 0, depth_sum / alpha.clamp_min(1e-10), torch.zeros_like(depth_sum))
            depths.append(depth.reshape(1, H, W))
        if return_alpha or cover < 1:
            alphas.append(alpha.reshape(1, H, W))
    rgb, alpha = torch.stack(rgbs), torch.stack(alphas) if alphas else None
    if cover < 1:
        rgb, alpha = covered(rgb, alpha, bg, cover)
    return RenderOutput(rgb=rgb, depth=torch.stack(depths) if return_depth else None,
                        alpha=alpha if return_alpha else None)  # fmt: skip


def check_cover(cover: float) -> float:
    """``cover`` as a float in (0, 1], else a ValueError naming it."""
    if not 0 < float(cover) <= 1:  # NaN fails too
        raise ValueError(f"render: cover must be in (0, 1], got {cover}")
    return float(cover)


def covered(rgb: torch.Tensor, alpha: torch.Tensor, background: torch.Tensor, cover: float
            ) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """``render``'s ``cover``: (..., 3, H, W) colour over ``background`` (3,) and (..., 1, H, W)
    alpha, with every pixel whose alpha reaches ``cover`` shown in its splats' colour alone
    (colour minus the background's share, divided by alpha) at alpha 1; the others unchanged.

    Example:
        >>> rgb, alpha = torch.full((1, 3, 1, 2), 0.4), torch.tensor([[[[0.5, 0.2]]]])
        >>> out, a = covered(rgb, alpha, torch.zeros(3), 0.3)
        >>> out[0, 0, 0].tolist(), a[0, 0, 0].tolist()
        ([0.800000011920929, 0.4000000059604645], [1.0, 0.20000000298023224])
    """
    seen = alpha >= cover
    own = (rgb - (1 - alpha) * background.reshape(3, 1, 1).to(rgb)) / alpha.clamp_min(cover)
    return torch.where(seen, own, rgb), torch.where(seen, torch.ones_like(alpha), alpha)
