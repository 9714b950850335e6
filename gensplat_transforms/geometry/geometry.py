"""Gaussians from RGB only: depth from a Pi3-compatible model, discs by the RGB-D rule.

The model (the official Pi3 checkpoint in the full configuration, or the shipped small
GenSplat model) predicts per-view depth (the z of its camera-frame point maps), confidences
and camera poses in one forward pass; only the geometry is used. The Gaussians are then the
RGB-D path's surface discs (:mod:`.rgbd`), coloured by the images, so a model whose Gaussian
head was never trained (Pi3's) still gives good Gaussians, and the cache stores only depth.
Depth Anything 3 (DA3-Small / DA3-Base, :mod:`..model.da3`: Apache-2.0 weights, unlike Pi3's
CC BY-NC) can take the model's place: depth up to scale like Pi3's, and its own focal lengths.

Frame and scale:

* calibrated views: every pixel sits on its ray of the calibrated camera at the predicted
  depth. With ``scale="metric"`` the depth is used as predicted (a model trained on metric
  geometry, as the shipped one); with ``"fit"`` it is multiplied by the ratio of the calibrated
  to the predicted camera-centre spread (what Pi3 needs: its geometry is up to scale; it
  relies on the predicted poses, which the small model gets wrong on wide real rigs). A
  single view has no spread: ``"fit"`` raises. ``"auto"`` is ``"fit"`` for a Pi3 checkpoint
  given by path or hub id, or a DA3 model, with two or more views, ``"metric"`` otherwise.
* uncalibrated views: the predicted cameras, the first view's camera frame as the world,
  focal lengths estimated from the point maps (DA3's predicted ones); depth as predicted.

The model runs at the nearest multiple of 14 of the input size, or within ``max_pixels``
(:func:`.feedforward.model_size`); the returned views (and so the cache) are at that size, with the
cameras scaled to it.

:meth:`~GeometryReconstructor.predict_depths` (what a cache build calls) runs the model on
several timesteps at once, ``batch_timesteps`` of them (by default on CUDA as many as keep
every tensor below 2**31 elements, up to 32: :func:`.feedforward.timesteps_per_pass`); each
timestep's result is :meth:`~GeometryReconstructor.predict_depth`'s.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import torch

from ..core.cameras import Cameras, rigid_inverse
from ..weights import DEFAULT_MODEL_DIR
from .base import DepthReconstructor, Reconstruction, Views, valid_depth
from .feedforward import (
    check_batch_timesteps,
    model_size,
    pixel_channels,
    run_model,
    timesteps_per_pass,
    weights_hash,
)
from .model import GenSplatModel
from .model.checkpoints import CONFIG_FILE, FORMAT_NAME, read_config, resolve
from .model.config import check_max_pixels
from .model.da3 import DepthAnything3, is_da3_checkpoint
from .model.frames import align_similarity, estimate_focal, transform_poses
from .model.moge import is_moge_checkpoint
from .rgbd import RGBDConfig, RGBDReconstructor, disc_identity

SCALES = ("auto", "metric", "fit")


def is_gensplat_checkpoint(source: str | Path) -> bool:
    """Whether a checkpoint directory / hub id holds this project's format (metric depth)
    rather than an official Pi3 checkpoint (depth up to scale)."""
    return read_config(resolve(source) / CONFIG_FILE).get("format") == FORMAT_NAME


def weights_licence(source: str | Path = DEFAULT_MODEL_DIR) -> str:
    """The licence of a checkpoint's weights, read from its config (nothing loaded): Depth
    Anything 3 Small/Base and the shipped model are Apache-2.0, MoGe-2's MIT, Pi3's CC BY-NC 4.0; a
    checkpoint trained with ``gensplat train-model`` carries its trainer's."""
    if is_da3_checkpoint(source):
        return "Apache-2.0 (Depth Anything 3)"
    if is_moge_checkpoint(source):
        return "MIT (MoGe-2)"
    if not is_gensplat_checkpoint(source):
        return "CC BY-NC 4.0 (Pi3's weights: non-commercial use only)"
    if resolve(source).resolve() == Path(DEFAULT_MODEL_DIR).resolve():
        return "Apache-2.0 (the small model shipped with gensplat-transforms)"
    return "as its trainer set it (a gensplat train-model checkpoint)"


class GeometryReconstructor(DepthReconstructor):
    """Images (calibrated or not) -> model depth -> RGB-D surface discs (module docstring).

    Args:
        model: a :class:`GenSplatModel`, or a checkpoint directory / hub id for
            ``GenSplatModel.from_pretrained`` (a Pi3 directory loads the full configuration;
            default: the shipped small model); or a :class:`DepthAnything3` (DA3-Small / DA3-Base,
            Apache-2.0 weights, depth up to scale), or its checkpoint, recognised by its config.
        min_conf: drop pixels whose sigmoid(confidence) is below this.
        scale: ``"auto"``, ``"metric"`` or ``"fit"`` (see the module docstring).
        discs: the surface-disc settings (``RGBDConfig``); default ``RGBDConfig`` with
            ``soften_noise`` off: a model's depth errors are not a sensor's noise
            (docs/reconstruction.md gives what softening them costs).
        max_pixels: run the model on at most this many pixels per view (its input shrunk,
            aspect kept, to :func:`.feedforward.model_size`; the depth, and so the cache, at that size).
            Default: the model's own (``GenSplatModel.max_pixels``, the size it was trained at:
            12,544 for the shipped model, 255,000 for Pi3), none for a model that does not say.
        device, autocast_dtype: where the model runs, and e.g. torch.bfloat16 for autocast.
        batch_timesteps: timesteps per forward pass in :meth:`predict_depths` (a cache build).
            None (default): automatic, as many as keep every intermediate tensor of the model
            below 2**31 elements, at most 32, on CUDA (docs/cache_at_scale.md); 1 on the CPU,
            where batching gains nothing. A given number is capped by the same 2**31 rule, so
            no value can overflow the 32-bit indexing of CUDA kernels; see
            :func:`.feedforward.timesteps_per_pass`. The model runs without its Gaussian head.
            It does not change the results, nor the identity.

    Example: calibrated RGB, depth from the shipped small model
        >>> from gensplat_transforms.data.scenes import TabletopScene, default_cameras
        >>> cameras = default_cameras(28, 28)[:2]  # the model takes multiples of 14 pixels
        >>> images, _ = TabletopScene(seed=0).render(cameras)
        >>> result = GeometryReconstructor().reconstruct(Views(images, cameras))
        >>> result.gaussians.means.shape
        torch.Size([1568, 3])
    """

    name = "geometry"

    def __init__(
        self,
        model: GenSplatModel | DepthAnything3 | str | Path = DEFAULT_MODEL_DIR,
        *,
        min_conf: float | None = None,
        scale: str = "auto",
        discs: RGBDConfig | None = None,
        max_pixels: int | None = None,
        device: str | torch.device | None = None,
        autocast_dtype: torch.dtype | None = None,
        batch_timesteps: int | None = None,
    ) -> None:
        check_batch_timesteps("GeometryReconstructor", batch_timesteps)
        if scale not in SCALES:
            raise ValueError(f"GeometryReconstructor: scale must be one of {SCALES}, got {scale!r}")
        if min_conf is not None and not 0 <= min_conf <= 1:
            raise ValueError(f"GeometryReconstructor: min_conf must be in [0, 1], got {min_conf}")
        self.metric = not isinstance(model, DepthAnything3)  # this project's checkpoints are metric
        if not isinstance(model, GenSplatModel | DepthAnything3):
            self.metric = is_gensplat_checkpoint(model)
            model = (DepthAnything3 if is_da3_checkpoint(model) else GenSplatModel).from_pretrained(model)
        self.model = model.eval() if device is None else model.to(device).eval()
        self.max_pixels = max_pixels if max_pixels is not None else model.max_pixels
        check_max_pixels("GeometryReconstructor", self.max_pixels)
        self.min_conf, self.scale, self.autocast_dtype = min_conf, scale, autocast_dtype
        self.batch_timesteps = batch_timesteps  # not in config(): batching does not change the results
        self._channels = pixel_channels(self.model, gaussians=False)
        self.discs = RGBDReconstructor(discs or RGBDConfig(soften_noise=False))
        self._weights = weights_hash(self.model)  # once: build a new reconstructor after changing weights

    def config(self) -> dict:
        return {
            "model": self.model.config.to_dict(), "weights": self._weights, "min_conf": self.min_conf,
            "scale": self.scale, "metric_model": self.metric, "discs": disc_identity(self.discs.cfg),
            "autocast_dtype": str(self.autocast_dtype) if self.autocast_dtype else None,
        } | ({"max_pixels": self.max_pixels} if self.max_pixels is not None else {})  # unset: identities as before

    @torch.no_grad()
    def predict_depth(self, views: Views) -> Views:
        """The views (V, 3, H, W) at the model's size (V, 3, h, w), with their depth (V, 1, h, w)
        (0 where invalid or below ``min_conf``) and cameras (the given ones at (h, w), or the
        predicted ones: see the module docstring), on the CPU."""
        out, images = run_model(self.model, views.images, self.autocast_dtype, self.max_pixels, gaussians=False)
        return self._depth_views(views, out, 0, images)

    @torch.no_grad()
    def predict_depths(self, views: Iterable[Views]) -> Iterator[Views]:
        """:meth:`predict_depth` of each of ``views`` (timesteps, in order), the model run once
        per chunk of consecutive timesteps of one image shape (V, 3, H, W) and camera presence,
        at most :meth:`timesteps_per_pass` long, on (B, V, 3, h, w). Read and yielded lazily:
        one chunk's views and outputs are held at a time. The scale fit (calibrated views) and
        the first view's frame and focal lengths (uncalibrated) are each timestep's own."""
        for chunk in self._chunks(views):
            out, images = run_model(self.model, torch.stack([v.images for v in chunk]), self.autocast_dtype,
                                    self.max_pixels, gaussians=False)  # fmt: skip
            for b, v in enumerate(chunk):
                yield self._depth_views(v, out, b, images[b])

    def timesteps_per_pass(self, views: int, height: int, width: int) -> int:
        """Timesteps per forward pass for ``views`` images of ``height x width`` (input pixels)
        in :meth:`predict_depths`: ``batch_timesteps`` or automatic, within the 2**31-element
        bound at the model's size (:func:`.feedforward.timesteps_per_pass`)."""
        h, w = model_size(height, width, self.max_pixels)
        device = self.model.image_mean.device
        return timesteps_per_pass(views, h, w, self._channels, device, self.batch_timesteps)

    def _chunks(self, views: Iterable[Views]) -> Iterator[list[Views]]:
        """Consecutive runs of ``views`` that one forward pass takes (see :meth:`predict_depths`)."""
        chunk, key, size = [], None, 1
        for v in views:
            V, _, H, W = v.images.shape
            k = (V, H, W, v.cameras is None)
            if chunk and (k != key or len(chunk) == size):
                yield chunk
                chunk = []
            if not chunk:
                key, size = k, self.timesteps_per_pass(V, H, W)
            chunk.append(v)
        if chunk:
            yield chunk

    def _depth_views(self, views: Views, out: dict[str, torch.Tensor], b: int, images: torch.Tensor) -> Views:
        """:meth:`predict_depth`'s result for timestep ``b`` of the model's outputs ``out``
        (each (B, V, ...)), the views it was given and the images (V, 3, h, w) the model saw."""
        h, w = images.shape[-2:]
        device = images.device
        local, c2w = out["local_points"][b].float(), out["camera_poses"][b].float()
        depth = local[..., 2]  # (V, h, w)
        if views.cameras is not None:
            cameras = views.cameras.resize(w, h)
            depth = depth * self._scale(c2w, cameras.c2w.to(c2w))
        else:
            first = rigid_inverse(c2w[0])
            poses = transform_poses(c2w, torch.ones((), device=device), first[:3, :3], first[:3, 3])
            if "intrinsics" in out:  # a model that predicts its focal lengths (DA3)
                fx, fy = out["intrinsics"][b, :, 0, 0].float(), out["intrinsics"][b, :, 1, 1].float()
            else:
                fx = fy = estimate_focal(local, torch.sigmoid(out["conf"][b])).clamp_min(1.0)
            cameras = Cameras.from_intrinsics(fx, fy, w / 2, h / 2, poses, w, h)
        keep = valid_depth(depth)
        if self.min_conf is not None:
            keep &= torch.sigmoid(out["conf"][b].float()) >= self.min_conf
        depth = torch.where(keep, depth, torch.zeros_like(depth))
        return Views(images.cpu(), cameras.to(device="cpu"), depth[:, None].cpu())

    def _scale(self, predicted: torch.Tensor, calibrated: torch.Tensor) -> torch.Tensor:
        """Depth scale for calibrated views: 1, or calibrated / predicted camera-centre spread."""
        mode = self.scale if self.scale != "auto" else ("metric" if self.metric or len(predicted) < 2 else "fit")
        if mode == "metric":
            return torch.ones((), device=predicted.device)
        if len(predicted) < 2:
            raise ValueError("GeometryReconstructor: scale='fit' needs two or more views (one view's scale is "
                             "unobservable); use scale='metric' with a metric model")  # fmt: skip
        return align_similarity(predicted.double(), calibrated.double())[0].float()

    def assemble(self, views: Views) -> Reconstruction:
        return self.discs.assemble(views)
