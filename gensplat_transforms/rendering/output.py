"""How a rendered view becomes what an item holds, the same in the worker path and in
:func:`.batched.render_batch`: rendered with the config's backend over its background, holes
filled, depth where the view sees something, then resized and typed like the item's own images
and depth maps. :func:`render_views` makes all of an item's views in the worker path."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from ..core.cameras import Cameras
from ..core.views import nearest_pixels
from . import RenderOutput, render
from .holes import fill_holes

if TYPE_CHECKING:
    from ..core.views import Reconstruction
    from ..data.format import DepthSensor
    from ..settings import GenSplatConfig
    from ..views.perturbation import Perturbation

#: ``GenSplatConfig.depth_unit`` values: metres per unit of the item's depth maps, or None
DEPTH_UNITS = {None: None, "keep": None, "m": 1.0, "mm": 1e-3}
#: a view's depth counts where its alpha reaches this (elsewhere it shows nothing: depth 0)
DEPTH_MIN_ALPHA = 0.5


def render_views(stacks: Sequence[Sequence[Reconstruction]], moves: Sequence[Perturbation],
                 images: Sequence[torch.Tensor], depths: Sequence[torch.Tensor | None], config: GenSplatConfig,
                 sensors: dict[str, DepthSensor]) -> list[tuple[torch.Tensor, torch.Tensor | None]]:  # fmt: skip
    """An item's views, one (image, depth map or None) per replaced camera r (``config.replace``
    order): camera r of each of its stack's T reconstructions ``stacks[r]`` (one for a single
    image), moved by ``moves[r]`` (:meth:`.perturbation.Perturbation.move`, ``config.pivot_depth``),
    rendered (:func:`render_view`) like its image ``images[r]`` (..., 3, H, W)
    (:func:`like_images`) and, where its depth map ``depths[r]`` (..., 1, H', W') is given, its
    depth at the moved pose like that map in ``config.depth_unit`` (:func:`like_depth`): the
    view's own, or that of its depth sensor ``sensors[name]`` moved with it
    (:meth:`.data.format.DepthSensor.cameras`, :func:`render_depth`)."""
    out = []
    for name, stack, p, image, like in zip(config.replace, stacks, moves, images, depths):
        sensor = sensors.get(name) if like is not None else None
        rgbs, seen = [], []
        for rec in stack:
            target = p.move(rec.cameras, config.cameras.index(name), config.pivot_depth)
            view = render_view(rec, target, config, depth=like is not None and sensor is None)
            rgbs.append(view.rgb[0])
            seen.append(view.depth if sensor is None else render_depth(rec, sensor.cameras(target), config))
        rgb = like_images(torch.stack(rgbs), image).reshape(image.shape)
        depth = None if like is None else like_depth(torch.cat(seen), like, config.depth_unit).reshape(like.shape)
        out.append((rgb, depth))
    return out


def render_view(rec: Reconstruction, camera: Cameras, config: GenSplatConfig, depth: bool = False) -> RenderOutput:
    """The augmented view of ``camera`` (B cameras) as the transform makes it from ``rec``
    (its Gaussians as each camera composites them, :meth:`.views.Reconstruction.seen_from`,
    drawn with its render options), rendered with ``config.backend`` (the Gaussians' check is
    not repeated while torch saw no write to them: ``render``'s ``recheck``): rgb (B, 3, H, W),
    hole-filled with ``config.fill_holes``, the render's alpha (B, 1, H, W) (its coverage)
    and, with ``depth``, its depth (B, 1, H, W) in metres (:func:`seen_depth`; else None)."""
    def one(cameras: Cameras) -> RenderOutput:
        return render(rec.seen_from(cameras) if len(cameras) == 1 else rec.gaussians, cameras,
                      background=render_background(config), backend=config.backend, return_depth=depth,
                      recheck=False, **{**rec.render_options, **config.render_options})  # fmt: skip

    if rec.view_preference and len(camera) > 1:  # each camera composites the views its own way
        views = [one(camera[i]) for i in range(len(camera))]
        out = RenderOutput(*(torch.cat([getattr(v, k) for v in views]) if depth or k != "depth" else None
                             for k in ("rgb", "depth", "alpha")))  # fmt: skip
    else:
        out = one(camera)
    if depth:
        out.depth = seen_depth(out.depth, out.alpha)
    return filled(out, config)


def render_depth(rec: Reconstruction, camera: Cameras, config: GenSplatConfig) -> torch.Tensor:
    """(B, 1, H, W) depth in metres of ``camera`` (B cameras, e.g. a depth sensor beside the
    colour camera) as the transform renders depth maps (:func:`seen_depth`), with
    ``config.backend``: ``rec``'s Gaussians where they are (no view preference, which would
    move depth) with its render options."""
    out = render(rec.gaussians, camera, background=(0.0, 0.0, 0.0), backend=config.backend, return_depth=True,
                 recheck=False, **{**rec.render_options, **config.render_options})  # fmt: skip
    return seen_depth(out.depth, out.alpha)


def seen_depth(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """A render's expected depth where its alpha reaches ``DEPTH_MIN_ALPHA``, else 0 (nothing
    seen there: no depth, as a depth camera reports no return; holes are never filled with
    made-up depth)."""
    return torch.where(alpha >= DEPTH_MIN_ALPHA, depth, torch.zeros_like(depth))


def render_background(config: GenSplatConfig) -> tuple[float, float, float]:
    """What to render over: black when holes are filled afterwards, else ``config.background``."""
    return (0.0, 0.0, 0.0) if config.fill_holes else config.background


def filled(out: RenderOutput, config: GenSplatConfig) -> RenderOutput:
    """``out`` rendered over :func:`render_background`, its holes filled as ``config`` says."""
    if config.fill_holes:
        out.rgb = fill_holes(out.rgb, out.alpha, empty=config.background)
    return out


def as_cache_images(images: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(N, 3, H, W) uint8 or float images as float in [0, 1] at ``height x width`` (what a depth
    cache rebuilds the Gaussians from)."""
    images = images.float() / 255 if images.dtype == torch.uint8 else images.float()
    if images.shape[-2:] != (height, width):
        images = F.interpolate(images, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return images.clamp(0, 1)


def like_depth(depth: torch.Tensor, like: torch.Tensor, unit: str) -> torch.Tensor:
    """(N, 1, h, w) depth in metres as depth maps like ``like`` (..., 1, H, W) in ``unit``
    ("m" or "mm"): resized to H x W at the nearest pixels (never a mix of depths), in its
    dtype (integers rounded and clipped to the dtype's range)."""
    if depth.shape[-2:] != like.shape[-2:]:
        depth = nearest_pixels(depth, like.shape[-1], like.shape[-2])
    depth = depth / DEPTH_UNITS[unit]
    if like.is_floating_point():
        return depth.to(like.dtype)
    info = torch.iinfo(like.dtype)
    return depth.round().clamp(max(info.min, 0), info.max).to(like.dtype)


def like_images(rgb: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
    """(N, 3, h, w) renders as images like ``like`` (..., 3, H, W): resized to H x W, uint8 in
    [0, 255] or float in [0, 1] of its dtype (float images are taken to be in [0, 1], as
    LeRobot's are)."""
    if rgb.shape[-2:] != like.shape[-2:]:
        rgb = F.interpolate(rgb, size=like.shape[-2:], mode="bilinear", antialias=True, align_corners=False)
    rgb = rgb.clamp(0, 1)
    return (rgb * 255 + 0.5).to(torch.uint8) if like.dtype == torch.uint8 else rgb.to(like.dtype)
