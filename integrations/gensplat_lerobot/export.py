"""The Gaussians of one timestep of a LeRobot dataset as a 3DGS PLY file (``gensplat export-ply``)."""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path

from gensplat_transforms.core.atomic import atomic_write
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.data.outputs import check_output
from gensplat_transforms.geometry import make_reconstructor
from gensplat_transforms.transform import render_size

from .dataset import dataset_cache, load_settings
from .source import LeRobotSource

log = logging.getLogger(__name__)


def timestep_indices(meta, episode: int, frames: Iterable[int] | None = None) -> list[int]:
    """Indices in the whole dataset of ``frames`` of ``episode`` (default: all its frames;
    ``meta``: the dataset's ``LeRobotDatasetMetadata``). Raises ``ValueError`` naming the
    valid range when the episode or a frame is not in the dataset."""
    total = int(meta.total_episodes)
    if not 0 <= episode < total:
        raise ValueError(f"episode {episode} is not in the dataset, which has episodes 0..{total - 1}")
    start, length = int(meta.episodes["dataset_from_index"][episode]), int(meta.episodes["length"][episode])
    frames = range(length) if frames is None else list(frames)
    outside = [f for f in frames if not 0 <= f < length]
    if outside:
        raise ValueError(f"frame(s) {outside} not in episode {episode}, which has frames 0..{length - 1}")
    return [start + f for f in frames]


def timestep_gaussians(root: str | Path, repo_id: str, episode: int, frame: int) -> Gaussians:
    """The Gaussians GenSplat renders ``frame`` of ``episode`` from: read from the dataset's
    cache (``gensplat cache``'s settings and reconstructor), which builds the episode from the
    dataset first when it is missing or stale."""
    config, reconstructor = load_settings(root, repo_id)
    source = LeRobotSource(root, repo_id, config.cameras)
    timestep_indices(source.dataset.meta, episode, [frame])
    cache = dataset_cache(root, make_reconstructor(reconstructor), source)
    if cache.status(episode) != "ok":
        log.warning("episode %d is %s in the cache at %s: building it", episode, cache.status(episode), cache.root)
    cache.ensure(episode, source)
    if cache.kind != "depth":
        return cache.read(episode, frame).gaussians
    # the cache holds depth: the Gaussians are built from the frame's images at the render size
    views = source.views(episode, frame)
    width, height = render_size(views.images.shape[-1], views.images.shape[-2], config.render_scale)
    return cache.read(episode, frame, views.resized(width, height).images, (width, height)).gaussians


def export_ply(root: str | Path, repo_id: str, episode: int, frame: int, out: str | Path) -> Path:
    """Write :func:`timestep_gaussians` to ``out`` (a 3DGS binary PLY, :meth:`Gaussians.to_ply`;
    :func:`~gensplat_transforms.data.outputs.check_output`'s rule, written atomically); returns its path."""
    out = check_output(out, root)
    return atomic_write(out, timestep_gaussians(root, repo_id, episode, frame).to_ply)
