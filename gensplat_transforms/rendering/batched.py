"""Rendering the augmented views of a whole batch at once, after collation.

With ``GenSplatConfig.render_in="batch"`` the workers do the least they can: the transform
draws whether a sample is augmented and its perturbation exactly as ``"worker"`` does (the
same RNG calls, in the same order) and adds the moves, the cached cameras and the cached
depth as stored (two bytes a pixel) to the item (``plan.BATCH_KEYS``). :func:`render_batch`
decodes the depth and moves the cameras of the whole batch at once, rebuilds the Gaussians
of every augmented sample from that depth and the batch's own images with the PyTorch disc
rule (:func:`.geometry.rgbd.dense_discs`, in float32, compiled on CUDA), renders all target cameras,
fills the holes and writes the images back, in the images' dtype, range and size. On CUDA
all scenes go through one gsplat call; elsewhere (tests) each scene is rendered with
``config.backend``, through the same :func:`.render.output.render_view` as the worker, so the
images match the worker path's up to the disc rule's round-off.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import TYPE_CHECKING

import torch

from ..cache.depth_codec import depth_from_words
from ..core.cameras import Cameras
from ..core.gaussians import Gaussians
from ..core.sh import num_sh_bases
from ..core.views import Reconstruction, preferred_means, source_rays
from ..geometry import Reconstructor
from ..geometry.base import nearest_pixels
from ..geometry.rgbd import RGBDReconstructor, dense_discs, grid_pixel_ids, own_saturation
from ..views.perturbation import move_rig, scale_focal
from ..views.plan import BATCH_KEYS
from . import RenderOutput, render_size
from .gsplat_backend import render_gsplat_batch
from .output import (
    as_cache_images,
    filled,
    like_depth,
    like_images,
    render_background,
    render_depth,
    render_view,
    seen_depth,
)

if TYPE_CHECKING:
    from ..settings import GenSplatConfig
    from ..transform import GenSplatTransform


def disc_builder(reconstructor: Reconstructor) -> RGBDReconstructor:
    """The RGB-D disc rule that ``reconstructor`` assembles its cached depth with (the
    ``rgbd`` reconstructor itself, or the ``geometry`` reconstructor's discs); raises for
    reconstructors whose Gaussians the batch path cannot rebuild (TypeError)."""
    discs = reconstructor if isinstance(reconstructor, RGBDReconstructor) else getattr(reconstructor, "discs", None)
    if not isinstance(discs, RGBDReconstructor):
        raise TypeError(f"render_in='batch' rebuilds RGB-D discs from cached depth; the {reconstructor.name!r} "
                        "reconstructor's cache cannot be rendered that way: use render_in='worker'")  # fmt: skip
    return discs


@torch.no_grad()
def render_batch(batch: dict, transform: GenSplatTransform, backend: str | None = None,
                 compiled: bool | None = None) -> dict:  # fmt: skip
    """The collated ``batch`` of items from ``transform`` (``render_in="batch"``) with the
    augmented samples' replaced camera images rendered, and without ``BATCH_KEYS``.

    Renders where the batch's tensors are (move the batch to the GPU first) with ``backend``:
    by default "gsplat" (all scenes in one call) on CUDA, else ``transform.cfg.backend`` (one
    scene at a time). ``compiled``: build the discs with the rule compiled by ``torch.compile``
    (fused kernels; the first batch waits for the compilation; where it fails, a warning and
    the plain rule); default: on CUDA. The input is not modified.

    Example: a DataLoader whose workers only prepare the items, then one render per batch
        >>> import tempfile
        >>> from torch.utils.data import DataLoader
        >>> from gensplat_transforms import AugmentedDataset, GaussianCache, GenSplatConfig, GenSplatTransform, RGBDReconstructor
        >>> from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=4, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = GaussianCache(folder.name, RGBDReconstructor(), source.fingerprint)
        >>> transform = GenSplatTransform(GenSplatConfig(probability=1.0, render_in="batch"), cache, source)
        >>> batch = next(iter(DataLoader(AugmentedDataset(SceneDataset(source), transform), batch_size=4)))
        >>> batch["gensplat.depth"].shape  # (B, T, V, h, w): what the workers read from the cache
        torch.Size([4, 1, 2, 16, 16])
        >>> out = render_batch(batch, transform)  # on the GPU: render_batch(to_cuda(batch), transform)
        >>> out["observation.images.left"].shape, "gensplat.depth" in out
        (torch.Size([4, 3, 16, 16]), False)
        >>> folder.cleanup()
    """
    cfg = transform.cfg
    discs = disc_builder(transform.cache.reconstructor)
    out = {k: v for k, v in batch.items() if k not in BATCH_KEYS}
    rows = batch["gensplat.render"].nonzero()[:, 0]
    if len(rows) == 0:
        return out
    coded = batch["gensplat.coded"][rows].reshape(-1, 1, 1, 1, 1)
    first = batch[cfg.image_key.format(name=cfg.replace[0])]
    w, h = render_size(first.shape[-1], first.shape[-2], cfg.render_scale)
    words = batch["gensplat.depth"][rows]
    if words.shape[-2:] != (h, w):  # a cache smaller than the render: its pixels nearest the render's
        words = nearest_pixels(words, w, h)
    depth = depth_from_words(words, coded)  # (S, T, V, h, w)
    S, T = depth.shape[:2]
    images = torch.stack([_stacked(batch[cfg.image_key.format(name=n)][rows], T, h, w) for n in cfg.cameras], 2)
    rule = _compiled_discs if (compiled if compiled is not None else depth.device.type == "cuda") else dense_discs
    f32 = torch.float32
    means, quats, scales, dc, saturation, keep = (t.flatten(2, 3).flatten(0, 1) for t in rule(  # (S*T, V*n, ...)
        discs.disc_depth(depth), images, batch["gensplat.K"][rows].to(f32), batch["gensplat.c2w"][rows].to(f32),
        discs.cfg))  # fmt: skip
    sh = dc[:, :, None]
    if discs.cfg.sh_degree > 0:
        sh = torch.cat([sh, sh.new_zeros(*sh.shape[:2], num_sh_bases(discs.cfg.sh_degree) - 1, 3)], 2)
    views = [cfg.cameras.index(name) for name in cfg.replace]
    cached = batch["gensplat.c2w"][rows]  # (S, T, V, 4, 4); each sample's moves, the same at every frame
    sources = Cameras(batch["gensplat.K"][rows].flatten(0, 2), cached.flatten(0, 2), w, h)  # (S*T*V,): as cached
    V = len(cfg.cameras)
    moves = batch["gensplat.moves"][rows][:, None].expand(-1, T, -1, -1)  # (S, T, R, ROW)
    K = scale_focal(batch["gensplat.K"][rows][:, :, views], moves[..., 8]).flatten(0, 1)  # (S*T, R, 3, 3)
    c2w = move_rig(cached, moves, views, cfg.pivot_depth).flatten(0, 1)  # (S*T, R, 4, 4)
    opacity = discs.cfg.opacity
    style = discs.render_style()
    options = {**style["render_options"], **cfg.render_options}
    # each disc's own saturation (rough depth: plain Gaussians), unless the settings fix one
    saturation = saturation if "saturation" not in cfg.render_options else torch.full_like(saturation,
                                                                                           options["saturation"])
    depth_keys = {} if cfg.depth_unit in (None, "keep") else {
        r: key for r, name in enumerate(cfg.replace) if (key := cfg.image_key.format(name=name) + "_depth") in batch}  # fmt: skip
    backend = backend or ("gsplat" if depth.device.type == "cuda" else cfg.backend)
    if backend == "gsplat":
        background = torch.tensor(render_background(cfg)).to(depth)
        R, (M, N) = c2w.shape[1], keep.shape
        origins = sources.centers.to(means).reshape(M, V, 1, 3).expand(M, V, N // V, 3).reshape(M, N, 3)
        # each target camera composites the views its own way: one scene per (scene, camera)
        seen_means = preferred_means(means[:, None], source_rays(means, origins)[:, None], c2w[..., :3, 3].to(means),
                                     style["view_preference"])  # fmt: skip
        rgb, alpha, seen = render_gsplat_batch(
            seen_means.flatten(0, 1), *(t.repeat_interleave(R, 0) for t in (quats, scales)),
            (keep * opacity * saturation).repeat_interleave(R, 0), sh.repeat_interleave(R, 0),
            c2w.flatten(0, 1)[:, None], K.flatten(0, 1)[:, None], w, h, background, return_depth=bool(depth_keys),
            dilation=options["dilation"])  # fmt: skip
        rgb, alpha = rgb.reshape(M, R, *rgb.shape[2:]), alpha.reshape(M, R, *alpha.shape[2:])
        rgb = filled(RenderOutput(rgb.flatten(0, 1), alpha=alpha.flatten(0, 1)), cfg).rgb.unflatten(0, rgb.shape[:2])
        seen = None if seen is None else seen_depth(seen.reshape(M, R, *seen.shape[2:]), alpha)
    else:
        one = replace(cfg, backend=backend)
        scenes = zip(means, quats, scales, sh, saturation, keep, K, c2w, sources.K.unflatten(0, (-1, V)),
                     sources.c2w.unflatten(0, (-1, V)))  # fmt: skip
        views = [render_view(_scene(*discs_of_scene, Cameras(sk, st, w, h), discs), Cameras(k, t, w, h), one,
                             depth=bool(depth_keys))
                 for *discs_of_scene, k, t, sk, st in scenes]  # fmt: skip
        rgb = torch.stack([v.rgb for v in views])
        seen = torch.stack([v.depth for v in views]) if depth_keys else None
    rgb = rgb.unflatten(0, (S, T))  # (S, T, R, 3, h, w)
    for r, name in enumerate(cfg.replace):
        key = cfg.image_key.format(name=name)
        image = out[key] = batch[key].clone()
        image[rows] = like_images(rgb[:, :, r].flatten(0, 1), image).reshape(image[rows].shape)
        if r in depth_keys:
            like = out[depth_keys[r]] = batch[depth_keys[r]].clone()
            sensor = transform.depth_sensors.get(name)
            if sensor is None:
                rendered = seen.unflatten(0, (S, T))[:, :, r].flatten(0, 1)  # (S*T, 1, h, w) metres
            else:  # the depth sensor beside the moved camera
                sensor_c2w = sensor.pose(c2w[:, r])  # (S*T, 4, 4)
                sensor_K = sensor.K.to(c2w).expand(len(sensor_c2w), 3, 3)
                rendered = _render_depth(means, quats, scales, sh, saturation, keep, sources, discs, options, sensor_K,
                                         sensor_c2w, sensor.width, sensor.height, backend, cfg)  # fmt: skip
            like[rows] = like_depth(rendered, like[rows], cfg.depth_unit).reshape(like[rows].shape)
    return out


def _render_depth(means, quats, scales, sh, saturation, keep, sources: Cameras, discs: RGBDReconstructor, options: dict,
                  K: torch.Tensor, c2w: torch.Tensor, width: int, height: int, backend: str,
                  cfg: GenSplatConfig) -> torch.Tensor:  # fmt: skip
    """(S, 1, H, W) depth maps (:func:`.render.output.render_depth`) of the S scenes' discs (from
    the S * V ``sources``), each seen by one camera K (S, 3, 3), c2w (S, 4, 4) of ``width x
    height``, drawn with ``options``."""
    if backend == "gsplat":
        background = torch.zeros(3).to(means)
        _, alpha, depth = render_gsplat_batch(means, quats, scales, keep * discs.cfg.opacity * saturation,
                                              sh, c2w[:, None], K[:, None], width, height, background,
                                              return_depth=True, dilation=options["dilation"])  # fmt: skip
        return seen_depth(depth, alpha)[:, 0]
    one = replace(cfg, backend=backend)
    V = len(sources) // len(means)
    cams = zip(K, c2w, sources.K.unflatten(0, (-1, V)), sources.c2w.unflatten(0, (-1, V)))
    return torch.cat([render_depth(_scene(*g, Cameras(sk, st, sources.width, sources.height), discs),
                                   Cameras(k[None], t[None], width, height), one)
                      for *g, (k, t, sk, st) in zip(means, quats, scales, sh, saturation, keep, cams)])  # fmt: skip


_COMPILED: dict = {}  # the disc rule compiled by torch.compile, made once per process


def _compiled_discs(*args):
    """:func:`.geometry.rgbd.dense_discs` compiled by ``torch.compile`` (dynamic shapes:
    one compilation for any number of augmented samples); where compiling fails (no compiler,
    an unsupported device), a warning and the plain rule from then on."""
    if "rule" not in _COMPILED:
        _COMPILED["rule"] = torch.compile(dense_discs, dynamic=True)
    if _COMPILED["rule"] is not dense_discs:
        try:
            return _COMPILED["rule"](*args)
        except Exception as e:  # noqa: BLE001 - any compiler failure: the plain rule still works
            warnings.warn(f"render_batch: torch.compile of the disc rule failed ({type(e).__name__}: {e}); "
                          "using the plain rule", RuntimeWarning, stacklevel=3)  # fmt: skip
            _COMPILED["rule"] = dense_discs
    return dense_discs(*args)


def _stacked(images: torch.Tensor, T: int, height: int, width: int) -> torch.Tensor:
    """(S, [T,] 3, H, W) images of one camera as (S, T, 3, height, width) float in [0, 1]."""
    stack = images.flatten(0, 1) if images.ndim == 5 else images
    return as_cache_images(stack, height, width).unflatten(0, (images.shape[0], T))


def _scene(means, quats, scales, sh, saturation, keep, sources: Cameras, discs: RGBDReconstructor) -> Reconstruction:
    """One scene's discs (N, ...) where ``keep`` as the worker's reconstruction of them: its
    source cameras (V), pixel ids and render style."""
    V, (height, width) = len(sources), (sources.height, sources.width)
    ids = grid_pixel_ids(height, width, discs.cfg.stride, V).reshape(-1).to(keep.device)[keep]
    return Reconstruction(_scene_gaussians(means, quats, scales, sh, keep, discs.cfg.opacity), sources, ids,
                          **discs.render_style(own_saturation(saturation[keep].float(), discs.cfg)))  # fmt: skip


def _scene_gaussians(means, quats, scales, sh, keep, opacity: float) -> Gaussians:
    """One scene's discs (N, ...) where ``keep``, as float32 Gaussians in the worker's order."""
    means, quats, scales, sh = (t[keep].float() for t in (means, quats, scales, sh))
    return Gaussians(means, quats, scales, means.new_full((len(means),), opacity), sh)
