"""Gaussians from uncalibrated views with the feed-forward GenSplat model."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import torch
import torch.nn.functional as F

from ..core.cameras import Cameras, rigid_inverse
from ..core.gaussians import Gaussians
from ..weights import DEFAULT_MODEL_DIR
from .base import Reconstruction, Reconstructor, Views
from .model import PATCH_SIZE, GenSplatModel, to_gaussians
from .model.config import check_max_pixels
from .model.da3 import PRESETS as DA3_PRESETS
from .model.da3 import DepthAnything3
from .model.frames import align_similarity, estimate_focal, transform_gaussians, transform_poses


class GenSplatReconstructor(Reconstructor):
    """Images -> predicted cameras + one Gaussian per pixel (fewer with ``min_conf``).

    Frame of the result: when the views carry calibrated cameras, the Gaussians are put into the
    dataset's world and metres in one of two ways (``placement``):

    * ``"per_view"`` (default): only the predicted depth is kept. Each pixel's Gaussian sits
      on that pixel's ray of the calibrated camera at the predicted depth, oriented as the
      model predicted it relative to its view's camera; errors of the predicted poses and
      focal lengths do not misplace the views, and the given cameras reproduce the source
      views. The depth scale is the model's own (metric when it was trained on metric
      geometry, as the shipped model is), or the similarity's (below) with ``metric=False``;
    * ``"similarity"``: the whole prediction moves by the similarity that best matches the
      camera poses (rotation, centroid and spread of the centres; scale 1 for a single view).

    Without cameras, the first view's camera frame is the world (the model's own frame does not
    depend on view order, this convention does). The returned cameras are the given ones with
    ``per_view``; otherwise the predicted poses in the result's frame with intrinsics estimated
    from the point maps (principal point at the centre, focal at least 1 px), so rendering them
    reproduces the source views.

    Images whose size is not a multiple of 14 are resized to the nearest one for the model (or
    shrunk within ``max_pixels``, :func:`model_size`: one Gaussian per model pixel); the
    cameras are reported at the input size.

    Args:
        model: a :class:`GenSplatModel`, or a checkpoint directory / hub id for ``from_pretrained``
            (default: the shipped small model, ``gensplat_transforms/weights/small``).
        min_conf: drop pixels with sigmoid(conf) below this.
        placement: ``"per_view"`` or ``"similarity"``, for calibrated views (see above).
        metric: with ``per_view``, keep the model's scale (True) or use the camera spread's.
        max_pixels: run the model on at most this many pixels per view (default: no limit;
            unlike the geometry path's depth, the head's Gaussians lose more from fewer pixels
            than they gain in speed: docs/reconstruction.md).
        device: where the model runs (default: where its weights are).
        autocast_dtype: e.g. torch.bfloat16 to run the transformer under autocast.

    Example: uncalibrated RGB, the shipped small model predicts the cameras too
        >>> from gensplat_transforms.data.scenes import TabletopScene, default_cameras
        >>> images, _ = TabletopScene(seed=0).render(default_cameras(28, 28)[:2])
        >>> result = GenSplatReconstructor().reconstruct(Views(images))
        >>> len(result.cameras), result.gaussians.means.shape
        (2, torch.Size([1568, 3]))
    """

    name = "gensplat"

    def __init__(
        self,
        model: GenSplatModel | str | Path = DEFAULT_MODEL_DIR,
        *,
        min_conf: float | None = None,
        placement: str = "per_view",
        metric: bool = True,
        max_pixels: int | None = None,
        device: str | torch.device | None = None,
        autocast_dtype: torch.dtype | None = None,
    ):
        if not isinstance(model, GenSplatModel):
            model = GenSplatModel.from_pretrained(model)
        self.model = model.eval() if device is None else model.to(device).eval()
        self.max_pixels = max_pixels
        check_max_pixels("GenSplatReconstructor", max_pixels)
        if placement not in PLACEMENTS:
            raise ValueError(f"GenSplatReconstructor: placement must be one of {PLACEMENTS}, got {placement!r}")
        self.min_conf = min_conf
        self.placement = placement
        self.metric = bool(metric)
        self.autocast_dtype = autocast_dtype
        self._weights_hash: str | None = None

    def weights_hash(self) -> str:
        """:func:`weights_hash` of the model, computed once: build a new reconstructor after
        changing the weights."""
        if self._weights_hash is None:
            self._weights_hash = weights_hash(self.model)
        return self._weights_hash

    def config(self) -> dict:
        return {
            "model": self.model.config.to_dict(),
            "weights": self.weights_hash(),
            "min_conf": self.min_conf,
            "placement": self.placement,
            "metric": self.metric,
            "autocast_dtype": str(self.autocast_dtype) if self.autocast_dtype else None,
        } | ({"max_pixels": self.max_pixels} if self.max_pixels is not None else {})  # unset: identities as before

    @torch.no_grad()
    def reconstruct(self, views: Views) -> Reconstruction:
        V, _, H, W = views.images.shape
        out, images = run_model(self.model, views.images, self.autocast_dtype, self.max_pixels)
        h, w = images.shape[-2:]
        device = images.device
        gaussians = to_gaussians(out, 0)
        c2w = out["camera_poses"][0]
        conf = torch.sigmoid(out["conf"][0])
        if views.cameras is not None and self.placement == "per_view":
            target = views.cameras.c2w.to(c2w)
            scale = torch.ones((), device=device) if self.metric else align_similarity(c2w, target)[0]
            n = h * w  # pixel-aligned, view-major: each view's share rotates with its camera...
            gaussians = Gaussians.cat([
                transform_gaussians(gaussians[v * n : (v + 1) * n], scale, *_onto(c2w[v], target[v], scale))
                for v in range(V)
            ])  # fmt: skip
            # ...and its centres sit on the calibrated rays at the predicted depth
            calibrated = views.cameras.resize(w, h).to(device=device, dtype=torch.float32)
            depth = scale * out["local_points"][0, ..., 2].reshape(V, n)
            gaussians.means = calibrated.unproject(_pixel_centres(h, w, device).expand(V, n, 2), depth).reshape(-1, 3)
            cameras = views.cameras
        else:
            if views.cameras is None:
                first = rigid_inverse(c2w[0])
                scale, R, t = torch.ones((), device=device), first[:3, :3], first[:3, 3]
            else:
                scale, R, t = align_similarity(c2w, views.cameras.c2w.to(c2w))
            poses = transform_poses(c2w, scale, R, t)
            gaussians = transform_gaussians(gaussians, scale, R, t)
            focal = estimate_focal(out["local_points"][0], conf).clamp_min(1.0)
            cameras = Cameras.from_intrinsics(focal, focal, w / 2, h / 2, poses, w, h).resize(W, H)
        if self.min_conf is not None:
            gaussians = gaussians[conf.reshape(-1) >= self.min_conf]
        return Reconstruction(gaussians, cameras)


def model_size(height: int, width: int, max_pixels: int | None = None) -> tuple[int, int]:
    """(h, w) the model sees an image of ``height x width`` at: the nearest multiples of 14
    (its patch size), or with ``max_pixels`` below the image's pixel count, multiples of 14
    within that many pixels at about the image's aspect ratio (shrunk, rounded, then a patch
    taken off while over: as Pi3's own loader caps its input; the cost of a forward pass grows
    faster than the pixel count).

    Example:
        >>> model_size(480, 640), model_size(480, 640, max_pixels=255_000)
        ((476, 644), (434, 574))
    """
    if max_pixels is not None and height * width > max_pixels:
        shrink, patches = math.sqrt(max_pixels / (height * width)), max(1, max_pixels // PATCH_SIZE**2)
        h, w = (max(1, round(s * shrink / PATCH_SIZE)) for s in (height, width))
        while h * w > patches:  # rounded over: a patch off the side that keeps the aspect best
            if (w > 1 and w * height > h * width) or h == 1:
                w -= 1
            else:
                h -= 1
        return h * PATCH_SIZE, w * PATCH_SIZE
    return tuple(max(1, round(s / PATCH_SIZE)) * PATCH_SIZE for s in (height, width))


def run_model(model: GenSplatModel | DepthAnything3, images: torch.Tensor, autocast_dtype: torch.dtype | None = None,
              max_pixels: int | None = None, gaussians: bool = True):  # fmt: skip
    """One forward pass on images resized to :func:`model_size` on the model's device
    (``gaussians=False``: a GenSplatModel's geometry alone, without its Gaussian head).

    ``images``: (V, 3, H, W), the views of one timestep, or (B, V, 3, H, W), B timesteps of the
    same size run as one batch. Returns the model's outputs (a batch of one, or of B: each
    output's first axis is the timestep) and the images it saw, (V, 3, h, w) or (B, V, 3, h, w).
    """
    *lead, V, _, H, W = images.shape
    h, w = model_size(H, W, max_pixels)
    device = model.image_mean.device
    images = images.to(device, torch.float32).reshape(-1, V, 3, H, W)
    if (h, w) != (H, W):
        flat = F.interpolate(images.flatten(0, 1), size=(h, w), mode="bilinear", antialias=True, align_corners=False)
        images = flat.reshape(-1, V, 3, h, w)
    with torch.autocast(device.type, dtype=autocast_dtype, enabled=autocast_dtype is not None):
        out = model(images) if gaussians or not isinstance(model, GenSplatModel) else model(images, gaussians=False)
    return out, (images if lead else images[0])


#: the most timesteps an automatic batch holds (:func:`timesteps_per_pass`; the GPU timings
#: that chose it: docs/cache_at_scale.md)
MAX_BATCH_TIMESTEPS = 32
#: a tensor must hold fewer elements than this: CUDA kernels that index with 32-bit integers
#: refuse more (``upsample_bilinear2d_nhwc only supports output tensors with less than INT_MAX
#: elements`` from the Gaussian head, 32 timesteps of 2 x 294 x 518)
INT_MAX = 2**31 - 1


def pixel_channels(model: GenSplatModel | DepthAnything3, gaussians: bool = True) -> int:
    """The most values per model-input pixel (per view) that any intermediate tensor of
    ``model``'s forward pass holds (with ``gaussians``: its Gaussian head included), so that
    timesteps x views x h x w x this bounds every tensor's element count.

    * GenSplatModel: its Gaussian head's full-resolution tensors, the upsampled DPT features
      concatenated with the RGB features (N, gs_features + gs_rgb_features, H, W): 288 in the
      full configuration, 64 in the shipped small one; without the head, the point map's 3;
    * DepthAnything3: its DPT head's, features / 2 channels upsampled to (H, W), 32 after the
      next convolution, ``features`` at 8/14 of the resolution (64 in all for DA3-Base);
    * the transformer tokens: (patches + extra tokens) x the widest activation (the MLP's
      hidden width) per 14 x 14 patch, at most (1 + extra tokens) x width / 196 a pixel.

    Attention scores are not counted: the fused attention kernels do not materialise them.
    """
    if isinstance(model, DepthAnything3):
        dim, _, features, stages = DA3_PRESETS[model.config.name]
        head = max(features // 2, 32, features * 64 // PATCH_SIZE**2 + 1, stages[0] * 16 // PATCH_SIZE**2 + 1)
        extra, width = 1, 4 * dim  # the [cls] / camera token
    else:
        cfg = model.config
        head = cfg.gs_features + cfg.gs_rgb_features if gaussians else 3
        extra = max(1 + cfg.enc_registers, cfg.dec_registers)
        width = max(int(cfg.dim * cfg.mlp_ratio), int(cfg.head_dim * cfg.mlp_ratio), 3 * cfg.dim, 3 * cfg.head_dim)
    return max(head, -(-(1 + extra) * width // PATCH_SIZE**2))


def timesteps_per_pass(views: int, height: int, width: int, channels: int, device: str | torch.device,
                       requested: int | None = None) -> int:  # fmt: skip
    """How many timesteps of ``views`` images of ``height x width`` model pixels one forward
    pass takes: ``requested``, or by default :data:`MAX_BATCH_TIMESTEPS` on CUDA and 1 on
    the CPU (where batching gains nothing); either way at most as many as keep every tensor
    below :data:`INT_MAX` elements (B x views x height x width x ``channels`` < INT_MAX, with
    :func:`pixel_channels`' ``channels``), and at least 1.

    Example: the full configuration (288 channels), two views, at 294x518 and at 182x322
        >>> timesteps_per_pass(2, 294, 518, 288, "cuda"), timesteps_per_pass(2, 182, 322, 288, "cuda")
        (24, 32)
    """
    fit = max(1, (INT_MAX - 1) // (views * height * width * channels))
    if requested is None:
        requested = MAX_BATCH_TIMESTEPS if torch.device(device).type == "cuda" else 1
    return min(requested, fit)


def check_batch_timesteps(owner: str, value: int | None) -> None:
    """Raise ValueError naming ``owner`` unless ``value`` is None (automatic) or an integer >= 1."""
    if value is not None and (type(value) is not int or value < 1):
        raise ValueError(f"{owner}: batch_timesteps must be an integer >= 1 or None (automatic), got {value!r}")


def weights_hash(model: torch.nn.Module) -> str:
    """SHA-256 (16 hex digits) of a model's state dict (keys and bytes)."""
    h = hashlib.sha256()
    for key, value in sorted(model.state_dict().items()):
        h.update(key.encode())
        h.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return h.hexdigest()[:16]


#: How calibrated views' Gaussians are placed (see :class:`GenSplatReconstructor`).
PLACEMENTS = ("per_view", "similarity")


def _pixel_centres(h: int, w: int, device) -> torch.Tensor:
    """(1, h * w, 2) pixel centres (u, v), row-major."""
    v, u = torch.meshgrid(torch.arange(h, device=device) + 0.5, torch.arange(w, device=device) + 0.5, indexing="ij")
    return torch.stack([u, v], -1).reshape(1, -1, 2)


def _onto(source: torch.Tensor, target: torch.Tensor, scale: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(R, t) of x -> scale R x + t taking camera-to-world ``source`` onto ``target`` (4, 4)."""
    R = target[:3, :3] @ source[:3, :3].T
    return R, target[:3, 3] - scale * R @ source[:3, 3]
