"""Rendering the augmented views of a whole batch at once, after collation.

With ``GenSplatConfig.render_in="batch"`` the workers do the least they can: the transform
draws whether a sample is augmented and its perturbation exactly as ``"worker"`` does (the
same RNG calls, in the same order) and adds the moves, the cached cameras and the cached
depth as stored (two bytes a pixel) to the item (``plan.BATCH_KEYS``). :func:`render_batch`
hands that depth and the batch's own images to the transform's cache reader, which rebuilds
the scenes of every augmented sample and timestep at once
(:meth:`.cache.reader.CacheReader.scenes`), and renders them with the worker's own function
(:func:`.output.views_like`: the moves, the render, holes, depth and the items' sizes and
dtypes), so the images match the worker path's up to the disc rule's round-off. On CUDA all
scenes go through one gsplat call.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from ..cache.reader import DepthStack
from ..core.views import as_cache_images
from ..views.plan import BATCH_KEYS
from . import render_size
from .output import views_like

if TYPE_CHECKING:
    from ..transform import GenSplatTransform


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
        >>> from gensplat_transforms import AugmentedDataset, SceneCache, GenSplatConfig, GenSplatTransform, RGBDReconstructor
        >>> from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=4, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = SceneCache(folder.name, RGBDReconstructor(), source.fingerprint)
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
    out = {k: v for k, v in batch.items() if k not in BATCH_KEYS}
    rows = batch["gensplat.render"].nonzero()[:, 0]
    if len(rows) == 0:
        return out
    stack = DepthStack(*(batch[k][rows] for k in ("gensplat.depth", "gensplat.coded", "gensplat.K", "gensplat.c2w")))
    first = batch[cfg.image_key.format(name=cfg.replace[0])]
    w, h = render_size(first.shape[-1], first.shape[-2], cfg.render_scale)
    S, T = stack.words.shape[:2]
    images = torch.stack([_stacked(batch[cfg.image_key.format(name=n)][rows], T, h, w) for n in cfg.cameras], 2)
    compiled = compiled if compiled is not None else stack.words.device.type == "cuda"
    scenes = transform.reader.scenes(stack, images, compiled=compiled)  # S * T scenes
    moves = batch["gensplat.moves"][rows][:, None].expand(-1, T, -1, -1).flatten(0, 1)  # (S*T, R, ROW)
    keys = [cfg.image_key.format(name=n) for n in cfg.replace]
    depth_keys = [None if cfg.depth_unit in (None, "keep") or k + "_depth" not in batch else k + "_depth" for k in keys]
    flat = [batch[k][rows].reshape(S * T, *batch[k].shape[-3:]) for k in keys]
    flat_depths = [None if k is None else batch[k][rows].reshape(S * T, *batch[k].shape[-3:]) for k in depth_keys]
    views = views_like(scenes, moves, cfg.replace, flat, flat_depths, cfg, transform.depth_sensors, backend)
    for key, depth_key, (rgb, depth) in zip(keys, depth_keys, views):
        for k, v in ((key, rgb), (depth_key, depth)):
            if k is not None:
                out[k] = batch[k].clone()
                out[k][rows] = v.reshape(out[k][rows].shape)
    return out


def _stacked(images: torch.Tensor, T: int, height: int, width: int) -> torch.Tensor:
    """(S, [T,] 3, H, W) images of one camera as (S, T, 3, height, width) float in [0, 1]."""
    stack = images.flatten(0, 1) if images.ndim == 5 else images
    return as_cache_images(stack, height, width).unflatten(0, (images.shape[0], T))
