"""Wrapping a LeRobotDataset with the GenSplat transform."""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

from lerobot.datasets.lerobot_dataset import LeRobotDataset
from safetensors import SafetensorError, safe_open

from gensplat_transforms.cache.distributed import OnDevice, Shard
from gensplat_transforms.cache.store import SceneCache, StaleCacheError
from gensplat_transforms.core.atomic import atomic_write_json, read_json_object
from gensplat_transforms.data.format import GENSPLAT_DIR
from gensplat_transforms.data.outputs import gensplat_subfolder
from gensplat_transforms.geometry import make_reconstructor
from gensplat_transforms.rendering.gsplat_backend import check_gsplat
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform
from gensplat_transforms.views.perturbation import get_range

from .source import (
    LeRobotSource,
    check_cameras,  # noqa: F401 (the CLI checks its --cameras with it from here)
    episode_table,
)

log = logging.getLogger(__name__)


def settings_path(root: str | Path) -> Path:
    return Path(root) / GENSPLAT_DIR / "config.json"


def content_path(root: str | Path) -> Path:
    """``<root>/gensplat/dataset.json``: the dataset's content when ``gensplat cache`` last ran
    (``fingerprint``, ``content``) and, for a model's reconstructor, its weights' licence
    (``weights_licence``; not part of the content or its fingerprint)."""
    return Path(root) / GENSPLAT_DIR / "dataset.json"


def weights_licence_of(reconstructor: dict) -> str | None:
    """The licence of the model weights a reconstructor spec uses (None for ``rgbd``: no model)."""
    if reconstructor["name"] == "rgbd":
        return None
    from gensplat_transforms.geometry.geometry import weights_licence
    from gensplat_transforms.weights import DEFAULT_MODEL_DIR

    return weights_licence(reconstructor.get("model") or DEFAULT_MODEL_DIR)


def cache_command(root: str | Path, repo_id: str | None) -> str:
    return f"gensplat cache --root {root} --repo-id {repo_id or '<id>'}"


def save_settings(root: str | Path, config: GenSplatConfig, reconstructor: dict, link_depth: bool = True) -> Path:
    """Store the transform settings beside the dataset (read by :func:`enable_gensplat`), and
    whether the cache links the depth sidecars or stores copies (:func:`dataset_cache`)."""
    return atomic_write_json(settings_path(root), {"transform": config.to_dict(), "reconstructor": reconstructor,
                                                   "link_depth": link_depth})  # fmt: skip


def load_settings(root: str | Path, repo_id: str | None = None) -> tuple[GenSplatConfig, dict]:
    """The settings :func:`save_settings` stored (``repo_id`` only completes the error message);
    ``ValueError`` naming the file and its fault where they are not such settings."""
    path = settings_path(root)
    if not path.exists():
        raise FileNotFoundError(
            f"GenSplat is enabled but {path} does not exist: run `{cache_command(root, repo_id)}` once to write "
            "the settings and build the Gaussian cache"
        )
    try:
        data = json.loads(path.read_text())
        return GenSplatConfig.from_dict(data["transform"]), dict(data["reconstructor"])
    except (ValueError, TypeError, KeyError, AttributeError, IsADirectoryError) as e:  # not JSON, fields wrong, a folder
        raise ValueError(f"{path}: not GenSplat settings ({type(e).__name__}: {e}); rewrite them with "
                         f"`{cache_command(root, repo_id)}`") from e  # fmt: skip


def default_reconstructor(source: LeRobotSource) -> dict:
    """RGB-D where every reconstructed camera has depth, else the geometry path (model depth,
    RGB-D discs): it matches the model's own Gaussian head at small perturbations, caches about
    100x fewer bytes, and works with Pi3 checkpoints (see the README's reconstructor guide)."""
    return {"name": "rgbd"} if source.has_depth() else {"name": "geometry"}


def dataset_cache(root: str | Path, reconstructor, source: LeRobotSource, link_depth: bool | None = None
                  ) -> SceneCache:  # fmt: skip
    """The cache of a dataset: ``<root>/gensplat/cache/<reconstructor identity>/`` (refused with
    ``ValueError`` where a symbolic link leads it out of ``gensplat/``); it links the
    depth sidecars unless ``link_depth`` is False (None: as ``gensplat cache`` stored it, so that
    episodes built later, e.g. by training, are stored as the others)."""
    if link_depth is None:
        link_depth = read_json_object(settings_path(root)).get("link_depth", True) is not False
    return SceneCache(gensplat_subfolder(root, "cache", reconstructor.identity()), reconstructor,
                         source.fingerprint, link_depth=link_depth)  # fmt: skip


def check_cache(transform: GenSplatTransform, episodes, repo_id: str) -> int:
    """How many of ``episodes`` the transform's cache holds, decided before training starts.

    Episodes missing (or built by another cache format) are built lazily by the workers; a
    WARNING says how many and which command builds them ahead. Raises
    :class:`~gensplat_transforms.cache.store.StaleCacheError` naming what differs when cache files
    were built from other dataset content (the dataset changed since ``gensplat cache``)."""
    cache, source = transform.cache, transform.source
    status = cache.statuses(episodes)  # one stat per episode file found valid before
    built_for = {_built_for(cache.path(e)) for e, s in status.items() if s == "stale"} - {None, source.fingerprint}
    command = cache_command(source.root, repo_id)
    if built_for:
        raise StaleCacheError(
            f"the dataset at {source.root} changed since its GenSplat cache was built ({what_differs(source)}): "
            f"run `{command}` to rebuild the cache before training"
        )
    todo = sum(s != "ok" for s in status.values())
    if todo:
        log.warning("GenSplat cache at %s lacks %d of %d episodes: the training workers build them as they first "
                    "need them, which slows training until they are built; run `%s` beforehand to build them ahead",
                    cache.root, todo, len(status), command)  # fmt: skip
    return len(status) - todo


def _built_for(path: Path) -> str | None:
    """The dataset fingerprint in a cache file's header (None when unreadable)."""
    try:
        with safe_open(str(path), framework="pt") as f:
            return (f.metadata() or {}).get("dataset")
    except (SafetensorError, OSError):
        return None


def what_differs(source: LeRobotSource) -> str:
    """What changed in ``source``'s content since ``gensplat cache`` recorded it."""
    then = read_json_object(content_path(source.root)).get("content")
    if not isinstance(then, dict):  # missing or unreadable
        return f"its content fingerprint is now {source.fingerprint}"
    now = json.loads(json.dumps(source.content))
    parts = [f"{key} {then.get(key)} -> {now[key]}" for key in ("episodes", "frames", "fps") if then.get(key) != now[key]]
    if then.get("cameras") != now["cameras"]:
        parts.append("the reconstructed cameras, their features or calibration")
    files = then.get("files", {})
    changed = [f"{d}/" for d in {**files, **now["files"]} if files.get(d) != now["files"].get(d)]
    if changed:
        parts.append("the files under " + ", ".join(changed))
    return "; ".join(parts) or f"cache files built for other content; the content now is {source.fingerprint}"


class GenSplatLeRobotDataset(LeRobotDataset):
    """A LeRobotDataset whose items pass through the GenSplat transform, then through
    LeRobot's own 2D image transforms (so those also apply to rendered views).
    Created by :func:`enable_gensplat`, never directly."""

    def __getitem__(self, idx):
        return self.augmented(idx)

    def augmented(self, idx, view: int | None = None) -> dict:
        """Item ``idx`` through GenSplat (``view``: which of the trajectory's
        ``views_per_source`` cameras, default drawn, as in training) and the 2D transforms."""
        item = super().__getitem__(idx)
        item = self.gensplat(item, None if view is None else self.gensplat.plan(item, view))
        if self.gensplat_image_transforms is not None:
            for cam in self.meta.camera_keys:
                if cam not in self.meta.depth_keys:
                    item[cam] = self.gensplat_image_transforms(item[cam])
        return item


def enable_gensplat(dataset: LeRobotDataset, config: GenSplatConfig | None = None,
                    reconstructor: dict | None = None) -> GenSplatLeRobotDataset:
    """Turn ``dataset`` (in place) into a :class:`GenSplatLeRobotDataset`.

    Settings default to ``<root>/gensplat/config.json``. Frame offsets of temporal image
    stacks are taken from the dataset's delta timestamps, the unit of its depth-map features
    from its ``depth_output_unit`` (they are rendered at the new pose too, unless the
    settings' ``depth_unit`` is "keep"). The cache is checked here, in the
    calling process (:func:`check_cache`): episodes it lacks are announced and built lazily
    from the dataset; a cache built from other content stops with an error. The dataset's
    ``gensplat_cached`` is then (episodes cached, episodes used). Raises if anything needed is
    missing: never a silent no-op.
    """
    if isinstance(dataset, GenSplatLeRobotDataset):
        return dataset
    if not isinstance(dataset, LeRobotDataset):
        raise TypeError(f"enable_gensplat: expected a LeRobotDataset, got {type(dataset).__name__}")
    if config is None:
        config, reconstructor = load_settings(dataset.root, dataset.repo_id)
    source = LeRobotSource(dataset.root, dataset.repo_id, config.cameras)
    rec = make_reconstructor(reconstructor or default_reconstructor(source))
    key = config.image_key.format(name=config.replace[0])
    deltas = (dataset.delta_timestamps or {}).get(key)
    if deltas is not None and config.frame_offsets is None:
        offsets = tuple(round(d * dataset.meta.fps) for d in deltas)
        config = replace(config, frame_offsets=offsets)
    if config.depth_unit is None:  # depth-map features come in the dataset's unit
        config = replace(config, depth_unit=dataset.depth_output_unit)
    sensors = {n: source.calibration[n].depth for n in source.sensors}  # unregistered depth maps
    transform = GenSplatTransform(config, dataset_cache(dataset.root, rec, source), source, sensors)
    episodes = range(dataset.meta.total_episodes) if dataset.episodes is None else dataset.episodes
    cached = check_cache(transform, episodes, dataset.repo_id)
    two_d = dataset.image_transforms
    dataset.set_image_transforms(None)  # re-applied after GenSplat, see __getitem__
    dataset.__class__ = GenSplatLeRobotDataset
    dataset.gensplat = transform
    dataset.gensplat_image_transforms = two_d
    dataset.gensplat_cached = (cached, len(episodes))
    return dataset


def check_options(source: LeRobotSource, config: GenSplatConfig, total: int, episodes) -> None:
    """ValueError for settings that would fail at first use (before :func:`prepare` writes anything):
    no episodes, episodes not in the dataset, an unknown level, a render backend this machine lacks."""
    if total == 0:
        raise ValueError(f"{source.root}: the dataset has no episodes to cache")
    missing = sorted(set(episodes) - set(range(total)))
    if missing:
        raise ValueError(f"{source.root}: episode(s) {missing} are not in the dataset (episodes 0..{total - 1})")
    get_range(config.level)
    if config.backend == "gsplat":
        try:
            check_gsplat()
        except RuntimeError as e:
            raise ValueError(f"{e}; or use --backend fast") from None


def prepare(root: str | Path, repo_id: str, config: GenSplatConfig, reconstructor: dict | None = None,
            episodes=None, progress: bool = True, shard: Shard | None = None, verify: bool = True,
            link_depth: bool = True, batch_timesteps: int | None = None) -> dict:
    """Write the settings beside the dataset and build its Gaussian cache (resumable).

    ``shard`` is this process's place among several (see :mod:`gensplat_transforms.cache.distributed`;
    default: the only process): it builds only its share of the episodes, and only rank 0
    writes the settings. The models (geometry, gensplat) run on ``shard.device`` (``cuda:<local
    rank>`` when CUDA is available). ``verify=False`` skips episodes whose header is valid
    without reading their data (see :func:`~gensplat_transforms.cache.builder.build_cache`).
    ``link_depth=False`` stores a compressed copy of the depth sidecars instead of linking them
    (see :class:`~gensplat_transforms.cache.store.SceneCache`). ``batch_timesteps``: the geometry
    reconstructor's timesteps per forward pass (default: automatic; not stored in the settings,
    it does not change the cache). Returns per-episode
    :class:`~gensplat_transforms.cache.store.CacheStats` of this process's episodes (None when the
    episode was already cached)."""
    from gensplat_transforms.cache.builder import build_cache, pivot_depth

    shard = shard or Shard()
    source = LeRobotSource(root, repo_id, config.cameras)
    total = len(episode_table(source.dataset.meta)["length"])
    episodes = range(total) if episodes is None else episodes
    check_options(source, config, total, episodes)
    reconstructor = reconstructor or default_reconstructor(source)
    if reconstructor["name"] == "gensplat" and shard.device.type == "cuda":
        rec = OnDevice(make_reconstructor(reconstructor), shard.device)
    elif reconstructor["name"] == "monocular":  # it returns its depth on the CPU itself
        rec = make_reconstructor(reconstructor, shard.device)
    elif reconstructor["name"] == "geometry":  # it returns its depth on the CPU itself
        options = {**reconstructor.get("options", {}), "batch_timesteps": batch_timesteps}
        rec = make_reconstructor({**reconstructor, "options": options}, shard.device)
    else:
        rec = make_reconstructor(reconstructor)
    gensplat_subfolder(root, "cache", rec.identity())  # before anything is written or measured
    if shard.rank == 0:
        if config.pivot_depth is None:  # one camera, or two whose axes do not cross at the scene
            config = replace(config, pivot_depth=pivot_depth(rec, source, episodes, progress=progress))
        save_settings(root, config, reconstructor, link_depth)
        record = {"fingerprint": source.fingerprint, "content": source.content}
        licence = weights_licence_of(reconstructor)
        if licence is not None:
            record["weights_licence"] = licence
        atomic_write_json(content_path(root), record)
    return build_cache(dataset_cache(root, rec, source, link_depth), source, episodes, progress, shard, verify)
