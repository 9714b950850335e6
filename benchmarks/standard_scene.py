"""The standard benchmark scene: the library's procedural tabletop seen by its three default
224x224 cameras, back-projected to one pixel-aligned Gaussian per source pixel (~150k).

The Gaussians come from :class:`RGBDReconstructor` on the exact RGB-D images of
:class:`TabletopScene`: discs lying in the surface (anisotropic wherever the surface is
oblique), ``sigma_px`` source pixels wide, opacity 0.9 +- 0.05, SH degree 3 with the image
colour in the DC term and small random higher-order coefficients (view-dependent colour,
so the full SH evaluation is exercised). ``sigma_px = 1.5`` gives about 11 M
(splat, pixel) pairs inside the splats' boxes in the target view, the workload DESIGN.md
section 2 measured; the reconstructor's own default (0.4) gives 1.8 M.
The target camera is the left source camera rotated 20 deg about the world x axis through
the pivot of the left and right cameras. Built with ``soften_noise`` off, so that rule does not
change the workload.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gensplat_transforms import Cameras, Gaussians, pivot_point
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.views.perturbation import perturb_pose

STANDARD_SIGMA_PX = 1.5


@dataclass
class StandardScene:
    """Attributes:
    gaussians: N Gaussians, float32, SH degree 3.
    sources: the 3 source cameras [left, right, front].
    target: the camera to render (1 camera).
    pivot: (3,) centre of the target rotation.
    """

    gaussians: Gaussians
    sources: Cameras
    target: Cameras
    pivot: torch.Tensor


def standard_scene(
    size: int = 224,
    seed: int = 0,
    sigma_px: float = STANDARD_SIGMA_PX,
    stride: int = 1,
    theta_deg: float = 20.0,
) -> StandardScene:
    """Build the standard scene.

    Args:
        size: source and target image side in pixels.
        seed: tabletop layout and the random opacity and SH jitter.
        sigma_px: splat size in source pixels (see the module docstring).
        stride: keep every stride-th source pixel in u and v (Gaussian density 1/stride^2).
        theta_deg: rotation of the target camera about the pivot.
    """
    sources = default_cameras(size, size)
    rgb, depth = TabletopScene(seed).render(sources)
    recon = RGBDReconstructor(sigma_px=sigma_px, opacity=0.9, sh_degree=3, stride=stride, soften_noise=False)
    g = recon(Views(rgb, sources, depth)).gaussians
    gen = torch.Generator().manual_seed(seed)
    n = len(g)
    sh = g.sh.clone()
    sh[:, 1:] = 0.03 * torch.randn(n, sh.shape[1] - 1, 3, generator=gen)
    opacities = g.opacities + 0.1 * (torch.rand(n, generator=gen) - 0.5)
    gaussians = Gaussians(means=g.means, quats=g.quats, scales=g.scales, opacities=opacities, sh=sh)

    pivot = pivot_point(sources.c2w[0], sources.c2w[1])
    target = sources[0].with_c2w(perturb_pose(sources.c2w[0], pivot, "x", theta_deg, 0.0)[None])
    return StandardScene(gaussians=gaussians, sources=sources, target=target, pivot=pivot)
