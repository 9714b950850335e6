"""What every layer shares about one timestep: its camera views (:class:`Views`) and its
reconstruction (:class:`Reconstruction`), below both ``model/`` and ``reconstruction/``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import torch
import torch.nn.functional as F

from .cameras import Cameras
from .gaussians import Gaussians
from .jit import _jit

#: Depths beyond this (metres) mark pixels without depth, like zero, negative and non-finite
#: ones: no sensor measures that far (such values are sentinels), and Gaussians built from
#: them would overflow float32.
MAX_VIEW_DEPTH = 1e6


def valid_depth(depth: torch.Tensor) -> torch.Tensor:
    """Bool mask, same shape as ``depth``, of the values that are depths: > 0 and
    <= ``MAX_VIEW_DEPTH`` (so NaN and +-Inf are not)."""
    return (depth > 0) & (depth <= MAX_VIEW_DEPTH)


def nearest_pixels(x: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """(..., H, W) values of any dtype at ``width x height``: each new pixel takes the value of
    the source pixel nearest its centre (PyTorch's "nearest-exact"), so depths are never mixed."""
    H, W = x.shape[-2:]
    rows = ((torch.arange(height, device=x.device) + 0.5) * (H / height)).long().clamp_(max=H - 1)
    cols = ((torch.arange(width, device=x.device) + 0.5) * (W / width)).long().clamp_(max=W - 1)
    return x[..., rows[:, None], cols]


def as_cache_images(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(N, 3, H, W) uint8 or float images as float in [0, 1] at ``height x width`` (what a depth
    cache rebuilds the Gaussians from)."""
    images = images.float() / 255 if images.dtype == torch.uint8 else images.float()
    if images.shape[-2:] != (height, width):
        images = F.interpolate(images, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return images.clamp(0, 1)


@dataclass
class Views:
    """The camera images of one timestep.

    Attributes:
        images: (V, 3, H, W) float in [0, 1].
        cameras: V calibrated cameras, or None for uncalibrated input.
        depths: (V, 1, H, W) metric camera-z depth, or None. Any values are accepted; zero,
            negative, non-finite and values beyond ``MAX_VIEW_DEPTH`` (1e6 m) mark pixels
            without depth (see :func:`valid_depth`), so a sensor's sentinel for "no return"
            (e.g. 1e10 or float32's largest value) yields no Gaussian.

    Example:
        >>> from gensplat_transforms.data.scenes import TabletopScene, default_cameras
        >>> cameras = default_cameras(16, 16)[:2]
        >>> images, depths = TabletopScene(seed=0).render(cameras)
        >>> len(Views(images, cameras, depths)), len(Views(images))  # calibrated RGB-D; RGB only
        (2, 2)
    """

    images: torch.Tensor
    cameras: Cameras | None = None
    depths: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.images.ndim != 4 or self.images.shape[1] != 3:
            raise ValueError(f"Views.images: expected (V, 3, H, W), got {tuple(self.images.shape)}")
        if not self.images.is_floating_point():
            raise ValueError(f"Views.images: expected float images in [0, 1], got {self.images.dtype}")
        # min and max propagate NaN and expose Inf: one pass, ~15x faster than isfinite().all()
        if self.images.numel() and not all(math.isfinite(x) for x in torch.aminmax(self.images.detach())):
            raise ValueError("Views.images: contains NaN or Inf")
        v, _, h, w = self.images.shape
        if self.cameras is not None and (
            len(self.cameras) != v or (self.cameras.height, self.cameras.width) != (h, w)
        ):
            raise ValueError(
                f"Views.cameras: need {v} cameras of size {w}x{h}, got {len(self.cameras)} of "
                f"{self.cameras.width}x{self.cameras.height}"
            )
        if self.depths is not None and tuple(self.depths.shape) != (v, 1, h, w):
            raise ValueError(f"Views.depths: expected shape {(v, 1, h, w)}, got {tuple(self.depths.shape)}")

    def __len__(self) -> int:
        return self.images.shape[0]

    def resized(self, width: int, height: int) -> Views:
        """The views at ``width x height``: images resized with area antialiasing, depth
        sampled at the source pixel nearest each new pixel centre (never a mix of depths across
        an edge), intrinsics scaled; ``self`` when the size is unchanged."""
        if self.images.shape[-2:] == (height, width):
            return self
        images = F.interpolate(self.images, size=(height, width), mode="bilinear", antialias=True,
                               align_corners=False)  # fmt: skip
        depths = None if self.depths is None else nearest_pixels(self.depths, width, height)
        cameras = None if self.cameras is None else self.cameras.resize(width, height)
        return Views(images.clamp(0, 1), cameras, depths)


@dataclass
class Reconstruction:
    """Gaussians of one timestep and the source cameras expressed in their frame (the given
    calibration, or the poses a feed-forward model predicted).

    ``pixel_ids`` (N,) int64 tells pixel-aligned Gaussians' source pixel, ``v * H * W + row *
    W + col``; caches use it to store the static part of a scene once. ``render_options``
    are the ``render.render`` options its Gaussians are drawn with (RGB-D discs: their
    ``dilation`` and ``saturation``, one number or (N,), one per Gaussian, where discs on
    noisy depth are drawn plain), and ``view_preference`` lets each view's Gaussians win
    where their camera saw the surface best (:meth:`seen_from`; needs ``pixel_ids``).
    """

    gaussians: Gaussians
    cameras: Cameras
    pixel_ids: torch.Tensor | None = None
    render_options: dict = field(default_factory=dict)
    view_preference: float = 0.0

    def seen_from(self, camera: Cameras) -> Gaussians:
        """The Gaussians as one camera (``len(camera) == 1``) composites them: with a
        ``view_preference``, moved away from it along its rays by :func:`preferred_means`."""
        if not self.view_preference or self.pixel_ids is None:
            return self.gaussians
        g = self.gaussians
        means = preferred_means(g.means, self.rays, camera.centers[0].to(g.means), self.view_preference)
        return Gaussians(means, g.quats, g.scales, g.opacities, g.sh, validate=False).mark_checked()

    @cached_property
    def rays(self) -> torch.Tensor:
        """(N, 3) unit directions from the camera that saw each Gaussian to it (computed once,
        whichever cameras render it)."""
        means = self.gaussians.means
        return pixel_rays(means, self.pixel_ids, self.cameras.centers.to(means), self.cameras.height * self.cameras.width)

    def __post_init__(self) -> None:
        ids = self.pixel_ids
        if ids is None:
            return
        if ids.dtype != torch.int64 or ids.shape != (len(self.gaussians),):
            raise ValueError(
                f"Reconstruction.pixel_ids: expected int64 of shape ({len(self.gaussians)},), "
                f"got {ids.dtype} of shape {tuple(ids.shape)}"
            )
        if len(ids):
            low, high = (int(v) for v in torch.aminmax(ids))
            pixels = len(self.cameras) * self.cameras.height * self.cameras.width
            if low < 0 or high >= pixels:
                raise ValueError(f"Reconstruction.pixel_ids: must lie in 0..{pixels - 1} (the {len(self.cameras)} "
                                 f"cameras' pixels), got {low}..{high}")  # fmt: skip


#: 1 - cos of the angle between a Gaussian's source ray and the viewing ray at which
#: :func:`preferred_means` pushes by the full ``strength`` (about 16 deg)
FULL_PREFERENCE = 0.04


def source_rays(means: torch.Tensor, origins: torch.Tensor) -> torch.Tensor:
    """(..., N, 3) unit directions from ``origins`` (..., N, 3), the centres of the cameras
    that saw each Gaussian, to its mean (zero where a mean is at its origin)."""
    return F.normalize(means - origins, dim=-1)


def pixel_rays(means: torch.Tensor, pixel_ids: torch.Tensor, centers: torch.Tensor, pixels: int) -> torch.Tensor:
    """:func:`source_rays` (N, 3) of pixel-aligned Gaussians (N, 3) from the centres (V, 3)
    of the cameras whose pixels (``pixel_ids // pixels``, ``pixels`` per view) they came
    from. Float32 CPU means (a dataloader worker's) take a compiled pass; anything else
    tensor operations."""
    if means.ndim != 2 or means.shape[1] != 3 or pixel_ids.shape != means.shape[:1] or centers.shape[-1:] != (3,):
        raise ValueError(f"pixel_rays: need means (N, 3), pixel_ids (N,) and centres (V, 3), got "
                         f"{tuple(means.shape)}, {tuple(pixel_ids.shape)}, {tuple(centers.shape)}")  # fmt: skip
    if means.device.type == "cpu" and means.dtype == torch.float32 and not means.requires_grad:
        out = np.empty(tuple(means.shape), np.float32)
        _rays(means.detach().contiguous().numpy(), pixel_ids.contiguous().numpy(), centers.float().contiguous().numpy(),
              pixels, out)  # fmt: skip
        return torch.from_numpy(out)
    views = (pixel_ids // pixels).to(centers.device)
    if len(views):  # no index from the end
        low, high = (int(v) for v in torch.aminmax(views))
        if low < 0 or high >= len(centers):
            raise IndexError("pixel_rays: a pixel id beyond the cameras' pixels")
    return source_rays(means, centers[views])


@_jit()
def _rays(means, pixel_ids, centers, pixels, out):
    """:func:`pixel_rays` of float32 (N, 3) ``means`` into ``out``, in float32 as ``F.normalize``."""
    tiny = np.float32(1e-12)
    for i in range(means.shape[0]):
        v = pixel_ids[i] // pixels
        if v < 0 or v >= centers.shape[0]:
            raise IndexError("pixel_rays: a pixel id beyond the cameras' pixels")
        x, y, z = means[i, 0] - centers[v, 0], means[i, 1] - centers[v, 1], means[i, 2] - centers[v, 2]
        norm = max(np.float32(math.sqrt(x * x + y * y + z * z)), tiny)
        out[i, 0], out[i, 1], out[i, 2] = x / norm, y / norm, z / norm


def preferred_means(means: torch.Tensor, rays: torch.Tensor, center: torch.Tensor, strength: float) -> torch.Tensor:
    """Means (..., N, 3) moved away from a camera at ``center`` (..., 3) along its rays, by
    ``strength`` times their distance to it, scaled down linearly while 1 - cos of the angle
    between the ray and the Gaussian's source ray (``rays`` (..., N, 3), :func:`source_rays`)
    is below ``FULL_PREFERENCE``. The image positions stay; where two cameras saw one surface,
    the camera whose view is closest to this one is drawn in front (front-to-back compositing
    sorts by depth), while the other's Gaussians still show where it alone saw the surface. At
    a source camera's own pose, its Gaussians stay put. One camera's (N, 3) float32 CPU means
    (a dataloader worker's) take a compiled pass; anything else the tensor rule below."""
    if means.shape != rays.shape:
        raise ValueError(f"preferred_means: means {tuple(means.shape)} and rays {tuple(rays.shape)} differ in shape")
    if (means.ndim == 2 and center.ndim == 1 and means.device.type == "cpu" and means.dtype == torch.float32
            and not (means.requires_grad or rays.requires_grad)):  # fmt: skip
        return _preferred_means_cpu(means, rays.float(), center, strength)
    ray = means - center[..., None, :]
    inverse = ray.square().sum(-1, keepdim=True).clamp_min(1e-30).rsqrt()  # a mean at the centre: no NaN
    cos = (ray * rays).sum(-1, keepdim=True) * inverse
    return torch.addcmul(means, ray, ((1 - cos) / FULL_PREFERENCE).clamp(0, 1) * strength)


@_jit()
def _prefer(means, rays, cx, cy, cz, strength, full, out):
    """:func:`preferred_means` of (N, 3) float32 ``means`` and ``rays`` for one camera centre
    (float32 ``cx``, ``cy``, ``cz``), in one pass of float32 arithmetic as the tensor rule's,
    into ``out`` (N, 3)."""
    one, zero, tiny = np.float32(1.0), np.float32(0.0), np.float32(1e-30)
    for i in range(means.shape[0]):
        rx, ry, rz = means[i, 0] - cx, means[i, 1] - cy, means[i, 2] - cz
        inverse = one / math.sqrt(max(rx * rx + ry * ry + rz * rz, tiny))
        cos = (rx * rays[i, 0] + ry * rays[i, 1] + rz * rays[i, 2]) * inverse
        k = min(max((one - cos) / full, zero), one) * strength
        out[i, 0] = means[i, 0] + rx * k
        out[i, 1] = means[i, 1] + ry * k
        out[i, 2] = means[i, 2] + rz * k


def _preferred_means_cpu(means: torch.Tensor, rays: torch.Tensor, center: torch.Tensor, strength: float) -> torch.Tensor:
    """:func:`preferred_means` for one camera, compiled, for (N, 3) float32 CPU tensors (a
    dataloader worker's Gaussians)."""
    m, r = means.contiguous().numpy(), rays.contiguous().numpy()
    out = np.empty_like(m)
    cx, cy, cz = (np.float32(c) for c in center.reshape(3).tolist())
    _prefer(m, r, cx, cy, cz, np.float32(strength), np.float32(FULL_PREFERENCE), out)
    return torch.from_numpy(out)
