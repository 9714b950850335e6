"""How rendered views become what an item holds, the same in the worker path and in
:func:`.batched.render_batch`: :func:`views_like` renders B scenes' moved cameras
(:func:`.scenes.render_scenes`) and gives them the size and dtype of the item's own images and
depth maps; :func:`render_views` does it for one item's stacks in the worker path."""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
import torch.nn.functional as F

from ..core.cameras import Cameras
from ..core.scenes import Scenes
from ..core.views import nearest_pixels
from . import RenderOutput
from .scenes import moved_cameras, render_scenes, scene_depth

if TYPE_CHECKING:
    from ..core.views import Reconstruction
    from ..data.format import DepthSensor
    from ..settings import GenSplatConfig

#: ``GenSplatConfig.depth_unit`` values: metres per unit of the item's depth maps, or None
DEPTH_UNITS = {None: None, "keep": None, "m": 1.0, "mm": 1e-3}


def views_like(scenes: Scenes, moves: torch.Tensor, names: Sequence[str], images: Sequence[torch.Tensor],
               depths: Sequence[torch.Tensor | None], config: GenSplatConfig, sensors: dict[str, DepthSensor],
               backend: str | None = None) -> list[tuple[torch.Tensor, torch.Tensor | None]]:  # fmt: skip
    """The views of the C cameras ``names`` of B ``scenes``, each moved by its row of ``moves``
    (B, C, ``perturbation.ROW``) about its rig's pivot (:func:`.scenes.moved_cameras`) and
    rendered (:func:`.scenes.render_scenes`, ``backend``), one (images, depth maps or None) per
    camera: like its ``images[c]`` (B, 3, H, W) (:func:`like_images`) and, where ``depths[c]``
    (B, 1, H', W') is given, its depth at the moved pose like that map in ``config.depth_unit``
    (:func:`like_depth`), the view's own or that of its depth sensor ``sensors[name]``."""
    cameras = moved_cameras(scenes, moves, [config.cameras.index(n) for n in names], config.pivot_depth)
    views = render_scenes(scenes, cameras, config, depth=[d is not None for d in depths], backend=backend,
                          sensors=[sensors.get(n) if d is not None else None for n, d in zip(names, depths)])  # fmt: skip
    return [(like_images(views.rgb[:, c], image),
             None if like is None else like_depth(views.depth[c], like, config.depth_unit))
            for c, (image, like) in enumerate(zip(images, depths))]  # fmt: skip


def render_views(stacks: Sequence[Sequence[Reconstruction]], moves: torch.Tensor, images: Sequence[torch.Tensor],
                 depths: Sequence[torch.Tensor | None], config: GenSplatConfig,
                 sensors: dict[str, DepthSensor]) -> list[tuple[torch.Tensor, torch.Tensor | None]]:  # fmt: skip
    """An item's views, one (image, depth map or None) per replaced camera r (``config.replace``
    order): its stack's T reconstructions ``stacks[r]`` as T scenes, camera r moved by its row
    of ``moves`` (R, ``perturbation.ROW``), like its image ``images[r]`` ([T,] 3, H, W) and
    depth map ``depths[r]`` ([T,] 1, H', W') or None (:func:`views_like`). Cameras whose stacks
    hold the same reconstructions are rendered in one call."""
    groups: dict[tuple[int, ...], list[int]] = {}
    for r, stack in enumerate(stacks):
        groups.setdefault(tuple(map(id, stack)), []).append(r)
    out: list = [None] * len(stacks)
    for rs in groups.values():
        scenes = Scenes.of(stacks[rs[0]])
        T = len(scenes)
        flat = [images[r].reshape(T, *images[r].shape[-3:]) for r in rs]
        flat_depths = [None if depths[r] is None else depths[r].reshape(T, *depths[r].shape[-3:]) for r in rs]
        views = views_like(scenes, moves[rs][None].expand(T, -1, -1), [config.replace[r] for r in rs], flat,
                           flat_depths, config, sensors)  # fmt: skip
        for r, (rgb, depth) in zip(rs, views):
            out[r] = (rgb.reshape(images[r].shape), None if depth is None else depth.reshape(depths[r].shape))
    return out


def render_view(rec: Reconstruction, camera: Cameras, config: GenSplatConfig, depth: bool = False) -> RenderOutput:
    """The view of ``camera`` (C cameras, of any size) as the transform makes it from ``rec``
    (:func:`.scenes.render_scenes` of one scene): rgb (C, 3, H, W), hole-filled with
    ``config.fill_holes``, the render's alpha (C, 1, H, W) (its coverage) and, with ``depth``,
    its depth (C, 1, H, W) in metres (:func:`.scenes.seen_depth`; else None)."""
    views = render_scenes(Scenes.of([rec]), camera, config, depth=depth)
    return RenderOutput(views.rgb[0], torch.cat(views.depth) if depth else None, views.alpha[0])


def render_depth(rec: Reconstruction, camera: Cameras, config: GenSplatConfig) -> torch.Tensor:
    """(C, 1, H, W) depth in metres of ``camera`` (C cameras, e.g. a depth sensor beside the
    colour camera) as the transform renders depth maps (:func:`.scenes.scene_depth`): ``rec``'s
    Gaussians where they are, with ``config.backend``."""
    return scene_depth(Scenes.of([rec]), camera, config)[0]


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
