"""The one way the transform renders views: :func:`render_scenes`, B scenes x C cameras each.

A dataloader worker calls it with the scenes of one item (B = its stack of timesteps), the
batch mode (``render_in="batch"``) with a whole training batch's; the cameras come from
:func:`moved_cameras`. On CUDA with gsplat installed every scene and camera goes through one
gsplat call; elsewhere each scene is drawn with ``config.backend`` (the compiled CPU renderer
by default). Either way: each camera composites the Gaussians its own way (view preference),
holes are filled, depth is kept where the view sees something, and a depth sensor beside a
camera sees the moved scene from its own pose.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from ..core.cameras import Cameras
from ..core.gaussians import Gaussians
from ..core.scenes import Scenes
from ..core.views import preferred_means
from ..views.perturbation import move_cameras
from . import RenderOutput, check_cover, covered, render
from .gsplat_backend import render_gsplat_batch
from .holes import fill_holes
from .projection import DILATION

if TYPE_CHECKING:
    from ..data.format import DepthSensor
    from ..settings import GenSplatConfig

#: a view's depth counts where its alpha reaches this (elsewhere it shows nothing: depth 0)
DEPTH_MIN_ALPHA = 0.5


@dataclass
class SceneViews:
    """What :func:`render_scenes` returns for B scenes x C cameras.

    Attributes:
        rgb: (B, C, 3, H, W) float32, holes filled as the config says.
        alpha: (B, C, 1, H, W) the render's coverage.
        depth: per camera, (B, 1, h, w) metres where asked for (the view's own size, or its
            depth sensor's), 0 where nothing is seen (:func:`seen_depth`); else None.
    """

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: tuple[torch.Tensor | None, ...]


def moved_cameras(scenes: Scenes, moves: torch.Tensor, views: Sequence[int], pivot_depth: float | None = None
                  ) -> Cameras:  # fmt: skip
    """The B x C cameras (scene by scene) of the scenes' source cameras ``views`` (C indices),
    each moved by its row of ``moves`` (B, C, ``perturbation.ROW``) about its rig's pivot
    (:func:`.views.perturbation.move_cameras`): what :meth:`.views.perturbation.Perturbation.move` does to one camera."""
    B, V = len(scenes), scenes.views
    K, c2w = move_cameras(*(t.unflatten(0, (B, V)) for t in (scenes.sources.K, scenes.sources.c2w)), moves, views,
                          pivot_depth)  # fmt: skip
    return scenes.sources._derive(K.flatten(0, 1), c2w.flatten(0, 1))  # a rigid motion of checked poses


def render_scenes(scenes: Scenes, cameras: Cameras, config: GenSplatConfig, *, depth: bool | Sequence[bool] = False,
                  sensors: Sequence[DepthSensor | None] | None = None, backend: str | None = None) -> SceneViews:  # fmt: skip
    """Views of B ``scenes``, each from its own C cameras, as the transform makes them.

    Args:
        scenes: what to draw (:class:`.core.scenes.Scenes`).
        cameras: B x C cameras, scene by scene (:func:`moved_cameras`), of one size.
        config: the transform's settings: ``backend``, ``render_options`` (over the scenes'
            own), ``fill_holes`` and ``background``.
        depth: whether to return each camera's depth (one bool, or one per camera);
            ``sensors``: per camera, its depth sensor (``DepthSensor``: depth from the sensor,
            moved with the camera, at its size) or None (the view's own depth).
        backend: default "gsplat" (one call for all) where the scenes are on CUDA and gsplat
            is installed, else ``config.backend`` scene by scene.
    """
    B = len(scenes)
    if B == 0 or len(cameras) % B:
        raise ValueError(f"render_scenes: {B} scenes need B x C cameras (C >= 1), got {len(cameras)}")
    C = len(cameras) // B
    depth = (depth,) * C if isinstance(depth, bool) else tuple(depth)
    sensors = tuple(sensors) if sensors is not None else (None,) * C
    if len(cameras) != B * C or len(depth) != C or len(sensors) != C:
        raise ValueError(f"render_scenes: {B} scenes need B x C cameras and a depth flag and sensor per camera, got "
                         f"{len(cameras)} cameras, {len(depth)} flags, {len(sensors)} sensors")  # fmt: skip
    options, saturation = _options(scenes, config, cover=not config.fill_holes)
    view_depth = any(d and s is None for d, s in zip(depth, sensors))
    background = (0.0, 0.0, 0.0) if config.fill_holes else config.background
    backend = _backend(scenes, config, backend)
    draw = _draw_gsplat if backend == "gsplat" else _draw_scene_by_scene
    out = draw(scenes, cameras, background, options, saturation, view_depth, backend)
    if config.fill_holes:
        out.rgb = fill_holes(out.rgb.flatten(0, 1), out.alpha.flatten(0, 1), empty=config.background
                             ).unflatten(0, (B, C))  # fmt: skip
    depths = []
    for c, (wanted, sensor) in enumerate(zip(depth, sensors)):
        if not wanted:
            depths.append(None)
        elif sensor is None:
            depths.append(seen_depth(out.depth[:, c], out.alpha[:, c]))
        else:  # the depth sensor beside the moved camera
            c2w = cameras.c2w.unflatten(0, (B, C))[:, c]
            beside = Cameras(sensor.K.to(c2w).expand(B, 3, 3), sensor.pose(c2w), sensor.width, sensor.height)
            depths.append(scene_depth(scenes, beside, config, backend)[:, 0])
    return SceneViews(out.rgb, out.alpha, tuple(depths))


def scene_depth(scenes: Scenes, cameras: Cameras, config: GenSplatConfig, backend: str | None = None) -> torch.Tensor:
    """(B, C, 1, H, W) depth in metres (:func:`seen_depth`) of B ``scenes`` seen by B x C
    ``cameras`` (scene by scene; e.g. depth sensors): the Gaussians where they are (no view
    preference, which would move depth), over nothing, drawn as :func:`render_scenes` draws them."""
    options, saturation = _options(scenes, config, cover=False)
    backend = _backend(scenes, config, backend)
    draw = _draw_gsplat if backend == "gsplat" else _draw_scene_by_scene
    out = draw(scenes, cameras, (0.0, 0.0, 0.0), options, saturation, True, backend, prefer=False)
    return seen_depth(out.depth, out.alpha)


def seen_depth(depth: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """A render's expected depth where its alpha reaches ``DEPTH_MIN_ALPHA``, else 0 (nothing
    seen there: no depth, as a depth camera reports no return; holes are never filled with
    made-up depth)."""
    return torch.where(alpha >= DEPTH_MIN_ALPHA, depth, torch.zeros_like(depth))


def _options(scenes: Scenes, config: GenSplatConfig, cover: bool) -> tuple[dict, float | None]:
    """The ``render`` options the scenes are drawn with (the config's over the scenes' own) but
    the saturation, and the saturation the config fixes (None: each Gaussian's own). ``cover``
    False leaves partly covered pixels as composited (where holes are filled, the fill blends
    them with their surroundings; depth reads the render's own alpha)."""
    options = {"dilation": DILATION, "cover": 1.0, **(scenes.render_options or {}), **config.render_options}
    options["cover"] = check_cover(options["cover"]) if cover else 1.0
    return options, options.pop("saturation", None)


def _backend(scenes: Scenes, config: GenSplatConfig, backend: str | None) -> str:
    """``backend``, or by default "gsplat" for scenes on CUDA with gsplat installed, else ``config.backend``."""
    if backend is not None:
        return backend
    return "gsplat" if scenes.means.is_cuda and importlib.util.find_spec("gsplat") is not None else config.backend


def _draw_scene_by_scene(scenes: Scenes, cameras: Cameras, background, options, saturation, depth, backend,
                         prefer: bool = True) -> RenderOutput:  # fmt: skip
    """Each scene with ``backend`` (``render``), each camera its own Gaussians where the scenes
    have a view preference (and ``prefer``); (B, C, ...) images."""
    B = len(scenes)
    C = len(cameras) // B
    rgbs, depths, alphas = [], [], []
    for b in range(B):
        g, own, rays = scenes.gaussians(b)
        kwargs = {"background": background, "backend": backend, "return_depth": depth, "recheck": False,
                  "saturation": own if saturation is None else saturation, **options}  # fmt: skip
        if rays is None or not prefer:
            views = [render(g, cameras[b * C : (b + 1) * C], **kwargs)]
        else:  # each camera composites the views its own way
            views = [render(_seen_from(g, rays, cameras.c2w[i, :3, 3], scenes.view_preference), cameras[i], **kwargs)
                     for i in range(b * C, (b + 1) * C)]  # fmt: skip
        rgbs.append(torch.cat([v.rgb for v in views]))
        alphas.append(torch.cat([v.alpha for v in views]))
        depths.append(torch.cat([v.depth for v in views]) if depth else None)
    return RenderOutput(torch.stack(rgbs), torch.stack(depths) if depth else None, torch.stack(alphas))


def _seen_from(g: Gaussians, rays: torch.Tensor, center: torch.Tensor, strength: float) -> Gaussians:
    """Gaussians ``g`` as a camera at ``center`` (3,) composites them (:func:`.core.views.preferred_means`)."""
    means = preferred_means(g.means, rays, center.to(g.means), strength)
    return Gaussians(means, g.quats, g.scales, g.opacities, g.sh, validate=False).mark_checked()


def _draw_gsplat(scenes: Scenes, cameras: Cameras, background, options, saturation, depth, backend,
                 prefer: bool = True) -> RenderOutput:  # fmt: skip
    """All scenes and cameras in one gsplat call (padding drawn with opacity 0); (B, C, ...) images."""
    B = len(scenes)
    C = len(cameras) // B
    f32 = torch.float32
    K, c2w = (t.to(f32).unflatten(0, (B, C)) for t in (cameras.K, cameras.c2w))
    own = scenes.saturation if saturation is None else saturation
    opacities = scenes.opacities * own * scenes.keep
    bg = torch.as_tensor(background, dtype=f32, device=scenes.means.device)
    size = (cameras.width, cameras.height)
    if scenes.rays is None or not prefer:  # every camera of a scene sees the same Gaussians: B scenes x C cameras
        rgb, alpha, d = render_gsplat_batch(scenes.means, scenes.quats, scenes.scales, opacities, scenes.sh, c2w, K,
                                            *size, bg, return_depth=depth, dilation=options["dilation"])  # fmt: skip
    else:  # each camera its own means: B * C scenes of one camera
        means = preferred_means(scenes.means[:, None], scenes.rays[:, None], c2w[..., :3, 3].to(scenes.means),
                                scenes.view_preference)  # (B, C, N, 3)  # fmt: skip
        rgb, alpha, d = render_gsplat_batch(
            means.flatten(0, 1), *(t.repeat_interleave(C, 0) for t in (scenes.quats, scenes.scales, opacities, scenes.sh)),
            c2w.flatten(0, 1)[:, None], K.flatten(0, 1)[:, None], *size, bg, return_depth=depth,
            dilation=options["dilation"])  # fmt: skip
        rgb, alpha, d = (None if t is None else t.reshape(B, C, *t.shape[2:]) for t in (rgb, alpha, d))
    if options["cover"] < 1:
        rgb, alpha = covered(rgb, alpha, bg, options["cover"])
    return RenderOutput(rgb, d, alpha)
