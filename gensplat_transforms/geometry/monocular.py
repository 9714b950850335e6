"""Gaussians from RGB only, one image at a time: MoGe-2's metric depth, discs by the RGB-D rule.

MoGe-2 (:mod:`.model.moge`: MIT code and weights) predicts each view's metric point map from
that image alone. Calibrated views give it their horizontal field of view (the point map is
then fitted to the calibrated focal length; MoGe-2 assumes the principal point at the image
centre) and keep their cameras; the depth is used as predicted, in metres. An uncalibrated
timestep of one view gets MoGe-2's focal length, the principal point at the image centre and
the camera at the world origin. A single-image model gives no relative pose, so an
uncalibrated timestep of several views is refused: calibrate the cameras first (``gensplat
calibrate``).

A single image's metric scale is its own prediction, which wavers from frame to frame. The
frames of one run (:meth:`MonocularReconstructor.predict_depths`: a cache build's episode) are
aligned to each other: each camera's reference is the per-pixel median depth of the run's first
:data:`ALIGN_FRAMES` frames, and every frame's depth is divided by the median ratio of its
depth to the reference where both have depth (moving parts, a minority of the pixels, do not
move the median). :meth:`~MonocularReconstructor.predict_depth` of one timestep is its own
prediction, unaligned.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from pathlib import Path

import torch

from ..core.cameras import Cameras
from .base import DepthReconstructor, Reconstruction, Views
from .feedforward import weights_hash
from .model.moge import MoGe2, intrinsics_in_pixels
from .rgbd import RGBDConfig, RGBDReconstructor, disc_identity

#: frames of a run whose per-pixel median depth is each camera's reference scale
ALIGN_FRAMES = 16
#: the share of a view's pixels that must have depth in a frame and its reference to align it
MIN_SHARED = 0.05


class MonocularReconstructor(DepthReconstructor):
    """Images (calibrated, or one uncalibrated view) -> MoGe-2 depth -> RGB-D surface discs.

    Args:
        model: a :class:`.model.moge.MoGe2` or its checkpoint folder (``model.pt`` as published,
            or ``save_pretrained``'s pair); nothing is downloaded.
        num_tokens: ViT patches per image (the official default: 3600, ``resolution_level`` 9;
            fewer run faster and coarser).
        discs: the surface-disc settings (``RGBDConfig``; default with ``soften_noise`` off, as
            for the geometry reconstructor: model depth is smooth).
        device: where the model runs (default: the CPU).

    """

    name = "monocular"
    #: each view is predicted alone (``calibration.estimate.predict_cameras`` runs it per camera)
    single_image = True
    #: its depth is in metres
    metric = True

    def __init__(self, model: MoGe2 | str | Path, *, num_tokens: int | None = None, discs: RGBDConfig | None = None,
                 device: str | torch.device | None = None) -> None:  # fmt: skip
        if not isinstance(model, MoGe2):
            model = MoGe2.from_pretrained(model)
        self.model = (model if device is None else model.to(device)).eval()
        self.num_tokens = self.model.num_tokens() if num_tokens is None else num_tokens
        if type(self.num_tokens) is not int or self.num_tokens < 1:
            raise ValueError(f"MonocularReconstructor: num_tokens must be a positive integer, got {num_tokens!r}")
        self.discs = RGBDReconstructor(discs or RGBDConfig(soften_noise=False))
        self._weights = weights_hash(self.model)  # once: build a new reconstructor after changing weights

    def config(self) -> dict:
        return {"model": self.model.config.to_dict(), "weights": self._weights, "num_tokens": self.num_tokens,
                "discs": disc_identity(self.discs.cfg)}  # fmt: skip

    @torch.no_grad()
    def predict_depth(self, views: Views) -> Views:
        """The views with MoGe-2's depth (V, 1, H, W) in metres (0 off its mask) and their cameras
        (the given ones, or for one uncalibrated view MoGe-2's), on the CPU."""
        V, _, H, W = views.images.shape
        if views.cameras is None and V > 1:
            raise ValueError(f"MonocularReconstructor: {V} uncalibrated views; a single-image model gives no "
                             "relative pose between them: calibrate the cameras first (gensplat calibrate)")  # fmt: skip
        fov_x = None
        if views.cameras is not None:
            fx = views.cameras.K[:, 0, 0].double()
            fov_x = torch.rad2deg(2 * torch.atan(W / (2 * fx))).float()
        out = self.model.infer(views.images, num_tokens=self.num_tokens, fov_x=fov_x)
        cameras = views.cameras
        if cameras is None:
            K = intrinsics_in_pixels(out["intrinsics"].double().cpu(), W, H)
            fx = float(K[0, 0, 0])
            if not (math.isfinite(fx) and fx > 0 and float(out["mask"].float().mean()) > 0):
                raise ValueError(f"MonocularReconstructor: MoGe-2 gave no usable camera for this image (fx = {fx:g} "
                                 "px, or nothing valid in its mask): give the camera's intrinsics (gensplat calibrate)")  # fmt: skip
            cameras = Cameras(K, torch.eye(4, dtype=torch.float64)[None], W, H)
        return Views(views.images, cameras, out["depth"][:, None].float().cpu())

    def predict_depths(self, views: Iterable[Views]) -> Iterator[Views]:
        """:meth:`predict_depth` of each of ``views`` (the timesteps of one run, in order), each
        camera's depth aligned in scale to the run's first frames (module docstring). Holds at
        most :data:`ALIGN_FRAMES` timesteps."""
        first, reference = [], None
        for v in views:
            out = self.predict_depth(v)
            if reference is not None:
                yield _aligned(out, reference)
                continue
            first.append(out)
            if len(first) == ALIGN_FRAMES:
                reference = _reference(first)
                yield from (_aligned(o, reference) for o in first)
        if reference is None and first:
            reference = _reference(first)
            yield from (_aligned(o, reference) for o in first)

    def assemble(self, views: Views) -> Reconstruction:
        return self.discs.assemble(views)


def _reference(frames: list[Views]) -> torch.Tensor:
    """(V, 1, H, W) per-pixel median of the frames' depth where they have it (0 where none has)."""
    depth = torch.stack([f.depths for f in frames])  # (F, V, 1, H, W)
    return torch.nanmedian(torch.where(depth > 0, depth, torch.nan), 0).values.nan_to_num(0.0)


def _aligned(frame: Views, reference: torch.Tensor) -> Views:
    """``frame`` with each camera's depth divided by the median ratio of it to ``reference`` on
    the pixels both have (unchanged where they share fewer than ``MIN_SHARED`` of its pixels)."""
    if reference.shape != frame.depths.shape:
        raise ValueError(f"MonocularReconstructor: the views of one run must share their shape, got "
                         f"{tuple(frame.depths.shape)} after {tuple(reference.shape)}")  # fmt: skip
    depths = frame.depths.clone()
    for c in range(len(depths)):
        both = (depths[c] > 0) & (reference[c] > 0)
        if both.float().mean() >= MIN_SHARED:
            depths[c] /= (depths[c][both] / reference[c][both]).median()
    return Views(frame.images, frame.cameras, depths)

