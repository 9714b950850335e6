"""The online GenSplat transform: replace camera images by views rendered from perturbed
poses, from cached Gaussians, inside dataloader workers (or, with ``render_in="batch"``,
prepare them in the workers for :func:`.batched.render_batch`)."""

from __future__ import annotations

import functools
import math
import time
from dataclasses import asdict, dataclass, field

import torch
import torch.nn.functional as F
from torch.utils.data import Dataset

from .cache import EpisodeSource, GaussianCache
from .cache_reader import CacheReader
from .cameras import Cameras
from .counters import SampleCounters
from .dataset_format import DepthSensor
from .gaussians import Gaussians
from .holes import fill_holes
from .perturbation import AXES, Perturbation, PerturbationRange, PerturbationSampler
from .reconstruction import Reconstruction
from .reconstruction.base import nearest_pixels
from .rendering import BACKENDS, RenderOutput, render

RENDER_IN = ("auto", "worker", "batch")
#: ``GenSplatConfig.depth_unit`` values: metres per unit of the item's depth maps, or None
DEPTH_UNITS = {None: None, "keep": None, "m": 1.0, "mm": 1e-3}
#: a view's depth counts where its alpha reaches this (elsewhere it shows nothing: depth 0)
DEPTH_MIN_ALPHA = 0.5
#: item keys the transform adds with ``render_in="batch"`` and ``render_batch`` removes
BATCH_KEYS = ("gensplat.render", "gensplat.depth", "gensplat.coded", "gensplat.K", "gensplat.c2w", "gensplat.moves")


@dataclass
class GenSplatConfig:
    """Settings of :class:`GenSplatTransform`.

    Attributes:
        cameras: the reconstructed (external) cameras, in the order the cache stores them.
            The first two define the pivot; one camera alone needs ``pivot_depth``. A wrist
            camera never belongs here.
        replace: cameras whose image is replaced (default: all of ``cameras``).
        image_key: item key of a camera's image; ``{name}`` is replaced by the camera name.
        probability: chance that a sample is augmented.
        level: a named level (see ``perturbation.LEVELS``) or a ``PerturbationRange``.
        mode: "episode" (one perturbation per trajectory, the paper's default) or "frame".
        views_per_source: distinct perturbed cameras per trajectory (the paper: ~3).
        seed: fixes the set of perturbations; which one a sample gets is drawn from torch's
            RNG, which DataLoader seeds per worker and per epoch.
        frame_offsets: frames of a temporal stack (T, C, H, W) relative to the item's frame
            (default: the T frames ending at it); clamped to the episode, as LeRobot pads.
        backend, render_options: renderer (a ``rendering.BACKENDS`` name, or "auto" as in
            ``render``) and its options; "fast" renders with one thread unless
            ``{"threads": n}`` is given.
        background: RGB where nothing was reconstructed (with ``fill_holes``: only where the
            view shows nothing at all).
        fill_holes: paint the pixels the Gaussians leave uncovered (parts of the new view no
            source camera saw) and soften silhouette edges with the surrounding colours
            (``holes.fill_holes``), instead of ``background``.
        report: add ``gensplat.*`` keys describing the perturbation to the item.
        render_scale: build and render the augmented views at this fraction of the item's
            image size, in (0, 1], then resize them to the image size (see
            :func:`render_size`): about scale^2 of the render's time, for about 1 dB PSNR
            per halving of the side, also at the size a policy shrinks the frames to
            (``benchmarks/render_scale.py``: 640x480 frames seen at 224x168, 27.6 dB at 1,
            26.4 at 0.5, 25.3 at 0.35). Render no smaller than the policy reads. Cached
            depth of another size (a geometry cache holds it at the model's input size) is
            taken at the pixels nearest the render's, so the views keep the images' detail.
        depth_unit: the unit of the depth maps an item carries for the replaced cameras, at
            ``<image key>_depth`` (LeRobot's depth-map features: its ``depth_output_unit``,
            "mm" or "m"): those are replaced by the depth of the view at the new pose, 0 where
            it shows nothing (as a depth camera reports no return; see :func:`render_view`).
            "keep" leaves them unchanged (then they no longer match an augmented view); None,
            the default, raises for an item that carries one (the LeRobot plugin sets the
            dataset's unit).
        render_in: "worker" renders in the transform; "batch" only reads the cache and draws
            the perturbation there, adding the inputs of :func:`.batched.render_batch` to the
            item, which renders a whole batch at once after collation (on the training GPU).
            "auto": batch where the LeRobot plugin trains on CUDA, else worker (a transform
            used on its own renders in the worker).
        pivot_depth: with one reconstructed camera, the distance in metres along its optical
            axis to the pivot (see :mod:`.perturbation`), needed by the transform; ``gensplat
            cache`` measures it (:func:`.episodes.scene_depth`). None with two or more cameras.

    Example:
        >>> config = GenSplatConfig(cameras=("left", "right"), replace=("left",), level="small")
        >>> config.replace, config.probability, config.views_per_source
        (('left',), 0.5, 3)
    """

    cameras: tuple[str, ...] = ("left", "right")
    replace: tuple[str, ...] | None = None
    image_key: str = "observation.images.{name}"
    probability: float = 0.5
    level: str | PerturbationRange = "train"
    mode: str = "episode"
    views_per_source: int = 3
    seed: int = 0
    frame_offsets: tuple[int, ...] | None = None
    backend: str = "fast"
    render_options: dict = field(default_factory=dict)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fill_holes: bool = True
    report: bool = False
    render_in: str = "auto"
    render_scale: float = 1.0
    depth_unit: str | None = None
    pivot_depth: float | None = None

    def __post_init__(self) -> None:
        self.cameras = tuple(self.cameras)
        self.replace = tuple(self.cameras if self.replace is None else self.replace)
        if not self.cameras:
            raise ValueError("GenSplatConfig.cameras: need at least one external camera")
        if self.pivot_depth is not None and (len(self.cameras) > 1 or not 0 < self.pivot_depth < math.inf):
            raise ValueError("GenSplatConfig.pivot_depth: a positive distance in metres for one reconstructed "
                             f"camera (two or more define the pivot); got {self.pivot_depth} for {self.cameras}")  # fmt: skip
        unknown = [c for c in self.replace if c not in self.cameras]
        if unknown:
            raise ValueError(f"GenSplatConfig.replace: {unknown} are not reconstructed cameras {self.cameras}")
        if not 0 <= self.probability <= 1:
            raise ValueError(f"GenSplatConfig.probability must be in [0, 1], got {self.probability}")
        if self.views_per_source < 1:
            raise ValueError(f"GenSplatConfig.views_per_source must be >= 1, got {self.views_per_source}")
        if self.backend not in (*BACKENDS, "auto"):
            raise ValueError(f"GenSplatConfig.backend: unknown {self.backend!r}; available {sorted(BACKENDS)} "
                             "or 'auto'")
        if not 0 < self.render_scale <= 1:
            raise ValueError(f"GenSplatConfig.render_scale must be in (0, 1], got {self.render_scale}")
        if self.render_in not in RENDER_IN:
            raise ValueError(f"GenSplatConfig.render_in must be one of {RENDER_IN}, got {self.render_in!r}")
        if self.depth_unit not in DEPTH_UNITS:
            raise ValueError(f"GenSplatConfig.depth_unit must be one of {tuple(DEPTH_UNITS)}, got {self.depth_unit!r}")

    def to_dict(self) -> dict:
        """The settings as plain values for JSON (a ``PerturbationRange`` level as a dict)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> GenSplatConfig:
        """The inverse of :meth:`to_dict`, also after JSON turned its tuples into lists.

        Example:
            >>> import json
            >>> config = GenSplatConfig(level=PerturbationRange((2.0, 4.0), (0.01, 0.02)), frame_offsets=(-1, 0))
            >>> GenSplatConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
            True
        """
        d = _tuples(d)
        if isinstance(d.get("level"), dict):
            d["level"] = PerturbationRange(**_tuples(d["level"]))
        return cls(**d)


def _tuples(d: dict) -> dict:
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}


def render_size(width: int, height: int, scale: float) -> tuple[int, int]:
    """(width, height) of the views rendered for ``width x height`` images at ``scale``
    (``GenSplatConfig.render_scale``), at least one pixel each.

    Example:
        >>> render_size(640, 480, 0.35)
        (224, 168)
    """
    return max(1, round(width * scale)), max(1, round(height * scale))


def render_view(gaussians: Gaussians, camera: Cameras, config: GenSplatConfig, depth: bool = False) -> RenderOutput:
    """The augmented view of ``camera`` (B cameras) as the transform makes it, rendered with
    ``config.backend``: rgb (B, 3, H, W), hole-filled with ``config.fill_holes``, the render's
    alpha (B, 1, H, W) (its coverage) and, with ``depth``, its depth (B, 1, H, W) in metres
    (:func:`seen_depth`; else None)."""
    out = render(gaussians, camera, background=render_background(config), backend=config.backend,
                 return_depth=depth, **config.render_options)  # fmt: skip
    if depth:
        out.depth = seen_depth(out.depth, out.alpha)
    return filled(out, config)


def render_depth(gaussians: Gaussians, camera: Cameras, config: GenSplatConfig) -> torch.Tensor:
    """(B, 1, H, W) depth in metres of ``camera`` (B cameras, e.g. a depth sensor beside the
    colour camera) as the transform renders depth maps (:func:`seen_depth`), with
    ``config.backend``."""
    out = render(gaussians, camera, background=(0.0, 0.0, 0.0), backend=config.backend, return_depth=True,
                 **config.render_options)  # fmt: skip
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
    (:class:`.dataset_format.DepthSensor`; LeRobot's RealSense recordings): their maps are
    rendered from the sensor moved with the camera, at its size.

    Example: augment every item of the procedural dataset
        >>> import tempfile
        >>> from gensplat_transforms import RGBDReconstructor, build_cache
        >>> from gensplat_transforms.episodes import SceneDataset, SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=2, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = GaussianCache(folder.name, RGBDReconstructor(), source.fingerprint)
        >>> stats = build_cache(cache, source, [0], progress=False)
        >>> transform = GenSplatTransform(GenSplatConfig(probability=1.0, report=True), cache)
        >>> item = transform(SceneDataset(source)[1])
        >>> item["observation.images.left"].shape, item["gensplat.applied"]  # left and right replaced
        (torch.Size([3, 16, 16]), tensor([True, True]))
        >>> folder.cleanup()
    """

    def __init__(self, config: GenSplatConfig, cache: GaussianCache, source: EpisodeSource | None = None,
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
        if len(config.cameras) == 1 and config.pivot_depth is None:
            raise ValueError(f"GenSplatTransform: one reconstructed camera ({config.cameras[0]}) needs "
                             "GenSplatConfig.pivot_depth, the distance to the pivot along its axis (gensplat cache "
                             "measures it)")  # fmt: skip
        if config.render_in == "batch" and not self.reader.batchable:
            raise ValueError(f"GenSplatTransform: render_in='batch' needs a depth cache (RGB-D or geometry "
                             f"reconstructor); {self.reader} stores Gaussians: use render_in='worker'")  # fmt: skip
        self.sampler = PerturbationSampler(config.level, mode=config.mode, seed=config.seed)
        #: set to count every item (augmented or not) and its time across workers
        self.counters: SampleCounters | None = None

    # ------------------------------------------------------------------ per item
    def __call__(self, item: dict) -> dict:
        start = time.perf_counter()
        for key in ("episode_index", "frame_index"):
            if key not in item:
                raise KeyError(f"GenSplatTransform: item has no {key!r}; keys: {sorted(item)}")
        keys = {n: self.cfg.image_key.format(name=n) for n in self.cfg.cameras}
        batch = self.cfg.render_in == "batch"
        _check_images(item, keys, self.cfg.cameras if batch else self.cfg.replace)
        depth_keys = self._depth_keys(item, keys)
        episode, frame = _index(item, "episode_index"), _index(item, "frame_index")
        out = dict(item)
        applied = bool(torch.rand(()) < self.cfg.probability)
        view = int(torch.randint(self.cfg.views_per_source, ()))
        report, moves = [], []
        frames = 0
        if applied or batch:  # the batch keys have the cache's image size even when not augmented
            frames = self.reader.frames(episode)
            if not 0 <= frame < frames:
                raise IndexError(f"GenSplatTransform: frame_index {frame} outside episode {episode} (0..{frames - 1})")
        read: dict[int, Reconstruction] = {}  # frame -> Gaussians, read once per item
        for ci, name in enumerate(self.cfg.replace):
            p = self.sampler.sample(episode, frame, view=view * len(self.cfg.replace) + ci) if applied else Perturbation()
            if applied and not batch:
                depth_key = depth_keys.get(name)
                out[keys[name]], depth = self._render_like(item, keys, (episode, frame, frames), name, p, read, depth_key)
                if depth_key is not None:
                    out[depth_key] = depth
            moves.append(p)
            report.append([float(applied), float(AXES.index(p.axis)), p.theta_deg, p.mu_m])
        if self.cfg.report:
            r = torch.tensor(report) if applied else torch.zeros(len(report), 4)
            out["gensplat.applied"] = r[:, 0].bool()
            out["gensplat.axis"] = r[:, 1].long()
            out["gensplat.theta_deg"] = r[:, 2]
            out["gensplat.mu_m"] = r[:, 3]
        if batch:
            out.update(self._batch_inputs(item, keys, (episode, frame, frames), applied, moves))
        if self.counters is not None:
            self.counters.add(applied, time.perf_counter() - start)
        return out

    def _render_like(self, item: dict, keys: dict[str, str], where: tuple[int, int, int], name: str,
                     p: Perturbation, read: dict[int, Reconstruction],
                     depth_key: str | None) -> tuple[torch.Tensor, torch.Tensor | None]:  # fmt: skip
        """Rendered replacements of ``item[keys[name]]`` and of its depth map ``item[depth_key]``
        (None: none) with their shapes and dtypes (:func:`like_images`, :func:`like_depth`);
        ``where``: the item's (episode, frame, frames in its episode)."""
        image = item[keys[name]]
        size = self._render_size(image)
        rgbs, depths = [], []
        episode = where[0]
        for k, (o, f) in enumerate(self._stack_frames(image, *where)):
            if f not in read:
                images = functools.partial(self._source_images, item, keys, k, o, episode, f, size)
                read[f] = self.reader.timestep(episode, f, size, images)
            target = p.move(read[f].cameras, self.cfg.cameras.index(name), self.cfg.pivot_depth)
            sensor = self.depth_sensors.get(name) if depth_key is not None else None
            out = render_view(read[f].gaussians, target, self.cfg, depth=depth_key is not None and sensor is None)
            rgbs.append(out.rgb[0])
            depths.append(out.depth if sensor is None else render_depth(read[f].gaussians, sensor.cameras(target), self.cfg))
        rgb = like_images(torch.stack(rgbs), image).reshape(image.shape)
        if depth_key is None:
            return rgb, None
        like = item[depth_key]
        return rgb, like_depth(torch.cat(depths), like, self.cfg.depth_unit).reshape(like.shape)

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

    def _stack_frames(self, image: torch.Tensor, episode: int, frame: int, frames: int) -> list[tuple[int, int]]:
        """(offset, frame) of each image of ``image``'s temporal stack, one for a single image;
        frames are clamped to the episode's ``frames`` (a stack reaching past it repeats its
        ends, as LeRobot pads)."""
        stack = 1 if image.ndim == 3 else image.shape[0]
        offsets = (0,) if image.ndim == 3 else self.cfg.frame_offsets or tuple(range(1 - stack, 1))
        if len(offsets) != stack:
            raise ValueError(f"GenSplatTransform: {len(offsets)} frame_offsets for a stack of {stack}")
        return [(o, min(max(frame + o, 0), frames - 1)) for o in offsets]

    def _batch_inputs(self, item: dict, keys: dict[str, str], where: tuple[int, int, int], applied: bool,
                      moves: list[Perturbation]) -> dict[str, torch.Tensor]:
        """The ``BATCH_KEYS`` of an item for :func:`.batched.render_batch`, of the same shapes
        whether augmented or not (zeros when not), so that default collation stacks them:
        ``gensplat.render`` () bool, augmented; ``gensplat.depth`` (T, V, h, w) int16, the
        cached depth of the V reconstructed cameras at the T frames of the stack as the cache
        stores it (two bytes a pixel, uncleaned: the batch side decodes and cleans it, see
        :func:`.depth_codec.depth_from_words`), at the render size of the first replaced
        camera's images (:func:`render_size`; the cached pixels nearest its pixel centres) where
        that fits in the cached size, else at the cached size (the batch side takes the nearest
        pixels: the same words, a fraction of the bytes) and ``gensplat.coded`` () bool, how it
        is coded; ``gensplat.K`` (T, V, 3, 3) and
        ``gensplat.c2w`` (T, V, 4, 4) float64, their cached cameras (intrinsics at the render
        size); ``gensplat.moves`` (R, 3) float64, the move of each of the R replaced cameras as
        (axis index, theta_deg, mu_m) (the batch side moves the cameras, all at once). Their
        images are taken from the batch, so every reconstructed camera must be stacked alike."""
        stacks = {tuple(item[keys[n]].shape[:-3]) for n in self.cfg.cameras}
        if len(stacks) > 1:
            raise ValueError(f"GenSplatTransform: render_in='batch' needs the images of {self.cfg.cameras} stacked "
                             f"alike, got stacks {sorted(stacks)}: use render_in='worker'")  # fmt: skip
        image = item[keys[self.cfg.replace[0]]]
        frames = [f for _, f in self._stack_frames(image, *where)]
        stack = self.reader.depth(where[0], frames, self._render_size(image), read=applied)
        moved = torch.tensor([[AXES.index(p.axis), p.theta_deg, p.mu_m] for p in moves], dtype=torch.float64)
        return dict(zip(BATCH_KEYS, (torch.tensor(applied), stack.words, torch.tensor(stack.coded), stack.K,
                                     stack.c2w, moved.reshape(len(self.cfg.replace), 3))))  # fmt: skip

    def _source_images(self, item: dict, keys: dict[str, str], k: int, offset: int, episode: int,
                       frame: int, size: tuple[int, int]) -> torch.Tensor:
        """(V, 3, h, w) float images of the reconstructed cameras at stack index ``k`` (frame
        ``frame``, offset ``offset`` from the item's), at ``size`` = (w, h) (a depth cache builds
        the Gaussians from them). Frames the item does not carry are read from the source."""
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
        >>> from gensplat_transforms.episodes import SceneDataset, SceneEpisodes
        >>> source = SceneEpisodes(num_episodes=1, num_frames=4, size=16)
        >>> folder = tempfile.TemporaryDirectory()
        >>> cache = GaussianCache(folder.name, RGBDReconstructor(), source.fingerprint)
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
