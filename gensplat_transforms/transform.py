"""The online GenSplat transform: replace camera images by views rendered from perturbed
poses, from cached Gaussians, inside dataloader workers (or, with ``render_in="batch"``,
prepare them in the workers for :func:`.batched.render_batch`)."""

from __future__ import annotations

import functools
import math
import time

import torch
from torch.utils.data import Dataset

from .cache.reader import CacheReader
from .cache.store import EpisodeSource, SceneCache
from .core.counters import SampleCounters
from .core.views import as_cache_images
from .data.format import DepthSensor
from .rendering import render_size
from .rendering.output import render_depth, render_view, render_views
from .settings import GenSplatConfig
from .views.perturbation import AXES, ROW
from .views.plan import BATCH_KEYS, ViewPlan

__all__ = ["BATCH_KEYS", "AugmentedDataset", "GenSplatConfig", "GenSplatTransform", "ViewPlan", "render_depth",
           "render_size", "render_view"]  # fmt: skip


class GenSplatTransform:
    """Callable on a dataset item (a dict); returns a new dict, never modifies its input.

    Gaussians come from ``cache``; episodes missing from it are built on first use from
    ``source`` with the cache's reconstructor (safe with several workers), or raise if no
    source is given; an episode file whose data fails its checksum is rebuilt the same way.
    A ``depth`` cache (see :mod:`.cache`) builds the Gaussians from the item's own images,
    so the item must carry the images of every reconstructed camera.
    Picklable (spawn workers). The ``gsplat`` backend renders on CUDA: use it with spawn
    workers (CUDA cannot be initialised in a forked worker) or in the main process.
    ``depth_sensors`` names the replaced cameras whose depth maps are their depth sensor's own
    (:class:`.data.format.DepthSensor`; LeRobot's RealSense recordings): their maps are
    rendered from the sensor moved with the camera, at its size.

    Example: augment every item of the procedural dataset
        >>> import tempfile
        >>> from gensplat_transforms import RGBDReconstructor, build_cache
        >>> from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=2, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = SceneCache(folder.name, RGBDReconstructor(), source.fingerprint)
        >>> stats = build_cache(cache, source, [0], progress=False)
        >>> transform = GenSplatTransform(GenSplatConfig(probability=1.0, report=True), cache)
        >>> item = transform(SceneDataset(source)[1])
        >>> item["observation.images.left"].shape, item["gensplat.applied"]  # left and right replaced
        (torch.Size([3, 16, 16]), tensor([True, True]))
        >>> folder.cleanup()
    """

    def __init__(self, config: GenSplatConfig, cache: SceneCache, source: EpisodeSource | None = None,
                 depth_sensors: dict[str, DepthSensor] | None = None) -> None:  # fmt: skip
        self.cfg = config
        self.cache = cache
        self.source = source
        #: what the transform reads from the cache (episodes built or rebuilt there)
        self.reader = CacheReader(cache, source)
        #: cameras whose depth maps are their depth sensor's own (not registered to the colour
        #: image): their maps are rendered from the sensor, moved with the camera
        self.depth_sensors = dict(depth_sensors or {})
        if source is not None and tuple(source.camera_names) != config.cameras:
            raise ValueError(
                f"GenSplatTransform: the source reconstructs {tuple(source.camera_names)}, "
                f"the config names {config.cameras}"
            )
        self.sampler = config.perturbations()
        if len(config.cameras) == 1 and config.pivot_depth is None and self.sampler.about_pivot:
            raise ValueError(f"GenSplatTransform: one reconstructed camera ({config.cameras[0]}) needs "
                             "GenSplatConfig.pivot_depth, the distance to the pivot along its axis (gensplat cache "
                             f"measures it), for the moves of sampler {config.sampler!r}")  # fmt: skip
        if config.render_in == "batch" and not self.reader.batchable:
            raise ValueError(f"GenSplatTransform: render_in='batch' needs a depth cache (RGB-D or geometry "
                             f"reconstructor); {self.reader} stores Gaussians: use render_in='worker'")  # fmt: skip
        #: set to count every item (augmented or not) and its time across workers
        self.counters: SampleCounters | None = None

    # ------------------------------------------------------------------ per item
    def plan(self, item: dict, view: int | None = None) -> ViewPlan:
        """Draw the item's :class:`.plan.ViewPlan` with the transform's perturbation sampler
        (:meth:`.plan.ViewPlan.draw`; ``view``: which of the trajectory's views, default
        drawn); ``transform(item, plan)`` replays it (previews, tests)."""
        return ViewPlan.draw(self.cfg, self.sampler, _index(item, "episode_index"), _index(item, "frame_index"), view)

    def __call__(self, item: dict, plan: ViewPlan | None = None) -> dict:
        """The item with its replaced cameras' images (and depth maps) rendered as ``plan``
        says (default: :meth:`plan` draws one): one read of the cache for every frame of the
        item's stacks (:meth:`.cache.reader.CacheReader.stacks`) and one render of all its views
        (:func:`.render.output.render_views`); with ``render_in="batch"``, one read of their
        stored depth (:meth:`.cache.reader.CacheReader.depth`) and no render."""
        start = time.perf_counter()
        for key in ("episode_index", "frame_index"):
            if key not in item:
                raise KeyError(f"GenSplatTransform: item has no {key!r}; keys: {sorted(item)}")
        keys = {n: self.cfg.image_key.format(name=n) for n in self.cfg.cameras}
        batch = self.cfg.render_in == "batch"
        _check_images(item, keys, self.cfg.cameras if batch else self.cfg.replace)
        depth_keys = self._depth_keys(item, keys)
        plan = self.plan(item) if plan is None else plan
        if not isinstance(plan, ViewPlan):
            raise TypeError(f"GenSplatTransform: plan must be a ViewPlan (GenSplatTransform.plan), got {type(plan).__name__}")
        if len(plan.moves) != len(self.cfg.replace):
            raise ValueError(f"GenSplatTransform: the plan moves {len(plan.moves)} cameras, the config replaces "
                             f"{self.cfg.replace}")  # fmt: skip
        episode, frame = _index(item, "episode_index"), _index(item, "frame_index")
        out = dict(item)
        inputs = self._batch_inputs(item, keys, episode, frame, plan) if batch else {}
        if plan.applied and not batch:
            images = [item[keys[n]] for n in self.cfg.replace]
            stacks = self.reader.stacks(episode, frame, [(self._offsets(i), self._render_size(i)) for i in images],
                                        functools.partial(self._source_images, item, keys, episode))  # fmt: skip
            depths = [item[depth_keys[n]] if n in depth_keys else None for n in self.cfg.replace]
            moves = torch.tensor(plan.rows, dtype=torch.float64).reshape(len(plan.rows), ROW)
            views = render_views(stacks, moves, images, depths, self.cfg, self.depth_sensors)
            for name, (image, depth) in zip(self.cfg.replace, views):
                out[keys[name]] = image
                if name in depth_keys:
                    out[depth_keys[name]] = depth
        if self.cfg.report:
            out.update(_report(plan))
        out.update(inputs)
        if self.counters is not None:
            self.counters.add(plan.applied, time.perf_counter() - start)
        return out

    def _depth_keys(self, item: dict, keys: dict[str, str]) -> dict[str, str]:
        """{camera: key} of the replaced cameras' depth maps the item carries (``<image
        key>_depth``) that are rendered at the new pose too (none with ``depth_unit="keep"``);
        raises without a ``depth_unit`` or for a map unlike its image."""
        found = {n: keys[n] + "_depth" for n in self.cfg.replace if keys[n] + "_depth" in item}
        if found and self.cfg.depth_unit is None:
            raise ValueError(f"GenSplatTransform: the item carries depth maps {sorted(found.values())} of replaced cameras: "
                             "set GenSplatConfig.depth_unit to their unit ('mm' or 'm', LeRobot's depth_output_unit) to "
                             "render them at the new pose too, or to 'keep' to leave them unchanged")  # fmt: skip
        if self.cfg.depth_unit == "keep":
            return {}
        for n, key in found.items():
            _check_depth_map(key, item[key], item[keys[n]])
            sensor = self.depth_sensors.get(n)
            if sensor is not None and tuple(item[key].shape[-2:]) != (sensor.height, sensor.width):
                raise ValueError(f"GenSplatTransform: {key}: maps of {item[key].shape[-1]}x{item[key].shape[-2]}, but "
                                 f"camera {n!r}'s depth sensor is {sensor.width}x{sensor.height} (its K is at its maps' "
                                 "size): fix the calibration's depth block")  # fmt: skip
        return found

    def _render_size(self, image: torch.Tensor) -> tuple[int, int]:
        """(width, height) of the views rendered to replace ``image`` (..., 3, H, W) (see
        :func:`render_size`)."""
        return render_size(image.shape[-1], image.shape[-2], self.cfg.render_scale)

    def _offsets(self, image: torch.Tensor) -> tuple[int, ...]:
        """The offset from the item's frame of each image of ``image``'s temporal stack:
        (0,) for a single image (3, H, W), ``frame_offsets`` or the T frames up to the item's
        for a stack (T, 3, H, W)."""
        if image.ndim == 3:
            return (0,)
        offsets = self.cfg.frame_offsets or tuple(range(1 - image.shape[0], 1))
        if len(offsets) != image.shape[0]:
            raise ValueError(f"GenSplatTransform: {len(offsets)} frame_offsets for a stack of {image.shape[0]}")
        return offsets

    def _batch_inputs(self, item: dict, keys: dict[str, str], episode: int, frame: int,
                      plan: ViewPlan) -> dict[str, torch.Tensor]:  # fmt: skip
        """The :data:`.plan.BATCH_KEYS` of an item for :func:`.batched.render_batch`, of the
        same shapes whether augmented or not (zeros when not), so that default collation stacks
        them: the stack's stored depth and cameras at the render size of the first replaced
        camera's images (:meth:`.cache.reader.CacheReader.depth`) and the plan's moves. Their
        images are taken from the batch, so every reconstructed camera must be stacked alike."""
        stacks = {tuple(item[keys[n]].shape[:-3]) for n in self.cfg.cameras}
        if len(stacks) > 1:
            raise ValueError(f"GenSplatTransform: render_in='batch' needs the images of {self.cfg.cameras} stacked "
                             f"alike, got stacks {sorted(stacks)}: use render_in='worker'")  # fmt: skip
        image = item[keys[self.cfg.replace[0]]]
        stack = self.reader.depth(episode, frame, self._offsets(image), self._render_size(image), read=plan.applied)
        moves = torch.tensor(plan.rows, dtype=torch.float64).reshape(len(plan.rows), ROW)
        return dict(zip(BATCH_KEYS, (torch.tensor(plan.applied), stack.words, torch.tensor(stack.coded), stack.K,
                                     stack.c2w, moves)))  # fmt: skip

    def _source_images(self, item: dict, keys: dict[str, str], episode: int, k: int, offset: int, frame: int,
                       size: tuple[int, int]) -> torch.Tensor:  # fmt: skip
        """(V, 3, h, w) float images of the reconstructed cameras at stack index ``k`` (frame
        ``frame`` of ``episode``, offset ``offset`` from the item's), at ``size`` = (w, h) (a
        depth cache builds the Gaussians from them). Frames the item does not carry are read
        from the source."""
        _check_images(item, keys, tuple(n for n in self.cfg.cameras if n not in self.cfg.replace))
        if any(item[keys[n]].ndim == 3 for n in self.cfg.cameras) and offset != 0:
            if self.source is None:
                raise ValueError(f"GenSplatTransform: frame offset {offset} is rendered but not every reconstructed "
                                 "camera's images are stacked in the item (a depth cache needs them), and no source "
                                 "was given to read them from")  # fmt: skip
            images = list(self.source.views(episode, frame).images)
        else:
            images = [item[keys[n]] if item[keys[n]].ndim == 3 else item[keys[n]][k] for n in self.cfg.cameras]
        width, height = size
        return torch.cat([as_cache_images(image[None], height, width) for image in images])


def _report(plan: ViewPlan) -> dict[str, torch.Tensor]:
    """The ``gensplat.*`` keys that describe ``plan`` (``GenSplatConfig.report``): applied (R,)
    bool; axis (R,) long, the index into ``perturbation.AXES`` (-1: another direction);
    theta_deg (R,) and mu_m (R,) float32; move (R, ``perturbation.ROW``) float32, the whole move
    (:meth:`.perturbation.Perturbation.as_row`); all zero where not applied."""
    R = len(plan.moves)
    if not plan.applied:
        return {"gensplat.applied": torch.zeros(R, dtype=torch.bool), "gensplat.axis": torch.zeros(R, dtype=torch.long),
                "gensplat.theta_deg": torch.zeros(R), "gensplat.mu_m": torch.zeros(R), "gensplat.move": torch.zeros(R, ROW)}  # fmt: skip
    axis = [AXES.index(p.axis) if isinstance(p.axis, str) else -1 for p in plan.moves]
    return {"gensplat.applied": torch.ones(R, dtype=torch.bool), "gensplat.axis": torch.tensor(axis),
            "gensplat.theta_deg": torch.tensor([p.theta_deg for p in plan.moves], dtype=torch.float32),
            "gensplat.mu_m": torch.tensor([p.mu_m for p in plan.moves], dtype=torch.float32),
            "gensplat.move": torch.tensor(plan.rows)}  # fmt: skip


def _check_images(item: dict, keys: dict[str, str], cameras: tuple[str, ...]) -> None:
    """The images of ``cameras`` in ``item`` (their ``keys``) exist and can be replaced or
    reconstructed from (:func:`_check_image`)."""
    missing = [keys[n] for n in cameras if keys[n] not in item]
    if missing:
        raise KeyError(f"GenSplatTransform: item lacks camera image(s) {missing}; keys: {sorted(item)}")
    for n in cameras:
        _check_image(keys[n], item[keys[n]])


def _check_image(key: str, image: torch.Tensor) -> None:
    """A camera image the transform can replace: (3, H, W) or (T, 3, H, W), uint8 or float."""
    if not isinstance(image, torch.Tensor):
        raise TypeError(f"GenSplatTransform: {key} is a {type(image).__name__}, expected a torch.Tensor")
    if image.ndim not in (3, 4) or image.shape[-3] != 3 or 0 in image.shape:
        raise ValueError(f"GenSplatTransform: {key}: expected (3, H, W) or (T, 3, H, W) images, got {tuple(image.shape)}")
    if image.dtype != torch.uint8 and not image.is_floating_point():
        raise ValueError(f"GenSplatTransform: {key}: images must be uint8 in [0, 255] or float in [0, 1], got {image.dtype}")
    if image.is_floating_point():
        lo, hi = (float(v) for v in torch.aminmax(image.float()))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise ValueError(f"GenSplatTransform: {key}: images must be finite, got NaN or Inf values")
        if lo < -1e-3 or hi > 1 + 1e-3:
            raise ValueError(f"GenSplatTransform: {key}: float images must be in [0, 1] (or uint8 in [0, 255]), "
                             f"got values in [{lo:g}, {hi:g}]")  # fmt: skip


def _index(item: dict, key: str) -> int:
    """``item[key]`` as an int: a Python or tensor integer, or a float without a fractional part."""
    value = float(item[key])
    if not value.is_integer():
        raise ValueError(f"GenSplatTransform: {key} must be an integer, got {value}")
    return int(value)


def _check_depth_map(key: str, depth: torch.Tensor, image: torch.Tensor) -> None:
    """A depth map the transform can replace: (1, H, W), or (T, 1, H, W) stacked as its image."""
    if not isinstance(depth, torch.Tensor):
        raise TypeError(f"GenSplatTransform: {key} is a {type(depth).__name__}, expected a torch.Tensor")
    if depth.ndim != image.ndim or depth.shape[-3] != 1 or depth.shape[:-3] != image.shape[:-3] or 0 in depth.shape:
        raise ValueError(f"GenSplatTransform: {key}: expected a depth map (1, H, W), stacked as its image "
                         f"{tuple(image.shape)}, got {tuple(depth.shape)}")  # fmt: skip
    if depth.dtype == torch.bool or depth.is_complex():
        raise ValueError(f"GenSplatTransform: {key}: depth must be float or integer, got {depth.dtype}")


class AugmentedDataset(Dataset):
    """Wrap any map-style dataset whose items are dicts: ``item = transform(dataset[i])``.

    The way to use GenSplat in a custom PyTorch DataLoader (works with spawn workers).

    Example: a DataLoader over the procedural dataset, about half the samples augmented
        >>> import tempfile
        >>> from torch.utils.data import DataLoader
        >>> from gensplat_transforms import RGBDReconstructor
        >>> from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=4, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = SceneCache(folder.name, RGBDReconstructor(), source.fingerprint)
        >>> transform = GenSplatTransform(GenSplatConfig(probability=0.5), cache, source)  # builds if missing
        >>> batch = next(iter(DataLoader(AugmentedDataset(SceneDataset(source), transform), batch_size=4)))
        >>> batch["observation.images.left"].shape
        torch.Size([4, 3, 16, 16])
        >>> folder.cleanup()
    """

    def __init__(self, dataset, transform: GenSplatTransform) -> None:
        self.dataset = dataset
        self.transform = transform

    def __len__(self) -> int:
        return len(self.dataset)

    def __getitem__(self, index: int) -> dict:
        return self.transform(self.dataset[index])
