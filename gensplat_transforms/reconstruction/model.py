"""Gaussians from uncalibrated views with the feed-forward GenSplat model."""

from __future__ import annotations

import hashlib
from pathlib import Path

import torch
import torch.nn.functional as F

from ..cameras import Cameras, rigid_inverse
from ..model import PATCH_SIZE, GenSplatModel, to_gaussians
from ..model.geometry import align_similarity, estimate_focal, transform_gaussians, transform_poses
from ..weights import DEFAULT_MODEL_DIR
from .base import Reconstruction, Reconstructor, Views


class GenSplatReconstructor(Reconstructor):
    """Images -> predicted cameras + one Gaussian per pixel (fewer with ``min_conf``).

    Frame of the result: when the views carry calibrated cameras, the prediction is moved onto
    them by the similarity that best matches the camera poses (rotation, centroid and spread of
    the centres; scale 1 for a single view), so the Gaussians live in the dataset's world and
    metres. Otherwise the first view's camera frame is the world (the model's own frame does not
    depend on view order, this convention does). The returned cameras are the predicted poses in
    that frame with intrinsics estimated from the point maps (principal point at the centre,
    focal at least 1 px), so rendering them reproduces the source views; they are not the given
    calibration.

    Images whose size is not a multiple of 14 are resized to the nearest one for the model; the
    cameras are reported at the input size.

    Args:
        model: a :class:`GenSplatModel`, or a checkpoint directory / hub id for ``from_pretrained``
            (default: the shipped small model, ``gensplat_transforms/weights/small``).
        min_conf: drop pixels with sigmoid(conf) below this.
        device: where the model runs (default: where its weights are).
        autocast_dtype: e.g. torch.bfloat16 to run the transformer under autocast.
    """

    name = "gensplat"

    def __init__(
        self,
        model: GenSplatModel | str | Path = DEFAULT_MODEL_DIR,
        *,
        min_conf: float | None = None,
        device: str | torch.device | None = None,
        autocast_dtype: torch.dtype | None = None,
    ):
        if not isinstance(model, GenSplatModel):
            model = GenSplatModel.from_pretrained(model)
        self.model = model.eval() if device is None else model.to(device).eval()
        self.min_conf = min_conf
        self.autocast_dtype = autocast_dtype
        self._weights_hash: str | None = None

    def weights_hash(self) -> str:
        """SHA-256 (16 hex digits) of the state dict; computed once, so build a new reconstructor
        after changing the weights."""
        if self._weights_hash is None:
            h = hashlib.sha256()
            for key, value in sorted(self.model.state_dict().items()):
                h.update(key.encode())
                h.update(value.detach().cpu().contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
            self._weights_hash = h.hexdigest()[:16]
        return self._weights_hash

    def config(self) -> dict:
        return {
            "model": self.model.config.to_dict(),
            "weights": self.weights_hash(),
            "min_conf": self.min_conf,
            "autocast_dtype": str(self.autocast_dtype) if self.autocast_dtype else None,
        }

    @torch.no_grad()
    def reconstruct(self, views: Views) -> Reconstruction:
        V, _, H, W = views.images.shape
        h, w = (max(1, round(s / PATCH_SIZE)) * PATCH_SIZE for s in (H, W))
        device = self.model.image_mean.device
        images = views.images.to(device, torch.float32)
        if (h, w) != (H, W):
            images = F.interpolate(images, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
        with torch.autocast(device.type, dtype=self.autocast_dtype, enabled=self.autocast_dtype is not None):
            out = self.model(images[None])
        gaussians = to_gaussians(out, 0, self.min_conf)
        c2w = out["camera_poses"][0]
        focal = estimate_focal(out["local_points"][0], torch.sigmoid(out["conf"][0])).clamp_min(1.0)
        if views.cameras is not None:
            scale, R, t = align_similarity(c2w, views.cameras.c2w.to(c2w))
        else:
            first = rigid_inverse(c2w[0])
            scale, R, t = torch.ones((), device=device), first[:3, :3], first[:3, 3]
        cameras = Cameras.from_intrinsics(focal, focal, w / 2, h / 2, transform_poses(c2w, scale, R, t), w, h)
        return Reconstruction(transform_gaussians(gaussians, scale, R, t), cameras.resize(W, H))
