"""The transform's settings (:class:`GenSplatConfig`) and the command-line flags made from them."""

from __future__ import annotations

import argparse
from dataclasses import asdict, dataclass, field

from .core.config_flags import add_flags, config_from_flags, flag
from .data.format import distinct_cameras
from .rendering import BACKENDS
from .rendering.output import DEPTH_UNITS
from .views.perturbation import SAMPLERS, PerturbationRange, _integer, get_range, make_sampler, sampler_kinds

RENDER_IN = ("auto", "worker", "batch")
#: ``GenSplatConfig.mode`` values
MODES = ("episode", "frame")
#: Bounds of the move settings, past which no augmented image shows the scene (docs/transform.md):
#: a camera shift (``shift_m``, a level's forward move ``mu_m``) of at most 1 m, a pivot at most
#: 100 m along camera 0's axis, and at most 1000 distinct cameras per trajectory (the paper's
#: gains saturate at about 3; each view's draws must stay below ``perturbation.KEY_LIMIT``).
MAX_SHIFT_M = 1.0
MAX_PIVOT_DEPTH_M = 100.0
MAX_VIEWS_PER_SOURCE = 1000
def _sampler_argument(text: str) -> str:
    """``--sampler``'s value, checked (:func:`.perturbation.sampler_kinds`)."""
    try:
        sampler_kinds(text)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e)) from None
    return text


@dataclass
class GenSplatConfig:
    """Settings of :class:`GenSplatTransform`.

    Attributes:
        cameras: the reconstructed (external) cameras, in the order the cache stores them.
            The first two define the pivot; one camera alone needs ``pivot_depth`` (unless
            ``sampler`` is "tilt", whose moves turn about the camera's own centre). A wrist
            camera never belongs here.
        replace: cameras whose image is replaced (default: all of ``cameras``).
        image_key: item key of a camera's image; ``{name}`` is replaced by the camera name.
        probability: chance that a sample is augmented.
        sampler: how the cameras move (:mod:`.perturbation`): "paper" (default), the paper's
            ``level``: rotation about world X or Y through the pivot and a forward step;
            "tilt", the camera turned about a random axis through its own centre by up to
            ``tilt_deg`` and a world shift up to ``shift_m`` per axis; "arc", a turn about the world's vertical through the pivot by
            up to ``arc_deg`` and a step up to ``shift_m`` along the viewing axis; "mix", one of
            the three per move; or several kinds separated by commas ("tilt,arc"), one of
            those per move.
        level: a named level (see ``perturbation.LEVELS``) or a ``PerturbationRange`` (the
            "paper" sampler's).
        tilt_deg, arc_deg, shift_m: the "tilt" and "arc" samplers' ranges.
        focal_scale: (low, high) range of a focal-length change drawn log-uniformly for every
            move, within ``perturbation.FOCAL_SCALE_LIMITS`` (principal point and image size
            kept; holes the wider view reveals are filled); (1, 1), the default, changes nothing.
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
        report: add ``gensplat.applied``, ``.axis``, ``.theta_deg``, ``.mu_m`` and ``.move``
            (the whole move as a ``Perturbation.as_row`` row) to the item.
        render_scale: build and render the augmented views at this fraction of the item's
            image size, in (0, 1], then resize them to the image size (see
            :func:`.rendering.render_size`): about scale^2 of the render's time, for some fidelity
            also at the size a policy shrinks the frames to (docs/transform.md, "Cost";
            ``benchmarks/render_scale.py``). Render no smaller than the policy reads. Cached
            depth of another size (a geometry cache holds it at the model's input size) is
            taken at the pixels nearest the render's, so the views keep the images' detail.
        depth_unit: the unit of the depth maps an item carries for the replaced cameras, at
            ``<image key>_depth`` (LeRobot's depth-map features: its ``depth_output_unit``,
            "mm" or "m"): those are replaced by the depth of the view at the new pose, 0 where
            it shows nothing (as a depth camera reports no return; see :func:`.rendering.output.render_view`).
            "keep" leaves them unchanged (then they no longer match an augmented view); None,
            the default, raises for an item that carries one (the LeRobot plugin sets the
            dataset's unit).
        render_in: "worker" renders in the transform; "batch" only reads the cache and draws
            the perturbation there, adding the inputs of :func:`.batched.render_batch` to the
            item, which renders a whole batch at once after collation (on the training GPU).
            "auto": batch where the LeRobot plugin trains on CUDA, else worker (a transform
            used on its own renders in the worker).
        pivot_depth: the distance in metres along camera 0's optical axis to the pivot (see
            :mod:`.perturbation`). One reconstructed camera needs it (for any sampler but
            "tilt"); with two or more, None puts the pivot where the axes of cameras 0 and 1
            cross. ``gensplat cache`` sets it (:func:`.cache.builder.pivot_depth`): the scene's
            depth for one camera, or for two whose axes do not cross in front of both near
            the scene.

    Example:
        >>> config = GenSplatConfig(cameras=("left", "right"), replace=("left",), level="small")
        >>> config.replace, config.probability, config.views_per_source
        (('left',), 0.5, 3)
    """

    # what is reconstructed and replaced
    cameras: tuple[str, ...] = ("left", "right")
    replace: tuple[str, ...] | None = field(default=None, metadata=flag("cameras whose image is replaced", nargs="+"))
    image_key: str = "observation.images.{name}"
    # how the cameras move
    probability: float = field(default=0.5, metadata=flag("chance a training sample is augmented"))
    sampler: str = field(default="paper", metadata=flag(
        "paper: the paper's --level moves; tilt: random-axis turns about the camera and shifts; "
        "arc: turns about the vertical; mix: one of the three per move; or several of them separated by "
        "commas, one of those per move (e.g. tilt,arc)", metavar="{" + ",".join(SAMPLERS) + "}",
        type=_sampler_argument))  # fmt: skip
    level: str | PerturbationRange = field(default="train", metadata=flag("perturbation level of the paper sampler"))
    tilt_deg: float = field(default=10.0, metadata=flag("tilt sampler: largest rotation, degrees"))
    arc_deg: float = field(default=45.0, metadata=flag("arc sampler: largest turn either way, degrees"))
    shift_m: float = field(default=0.03, metadata=flag("tilt and arc samplers: largest shift, metres"))
    focal_scale: tuple[float, float] = field(default=(1.0, 1.0), metadata=flag(
        "range of focal-length factors drawn for every move (0.001 to 1000), e.g. 0.8 1.25", nargs=2, type=float,
        metavar=("LOW", "HIGH")))  # fmt: skip
    mode: str = field(default="episode", metadata=flag(
        "episode: one perturbation per trajectory and view; frame: a new one every frame", choices=MODES))
    views_per_source: int = field(default=3, metadata=flag("distinct perturbed cameras per trajectory"))
    seed: int = field(default=0, metadata=flag("seed fixing the set of perturbations"))
    pivot_depth: float | None = field(default=None, metadata=flag(
        "metres along the first camera's axis to the point the moves turn about; unset, gensplat cache places it "
        "where the first two cameras' axes cross at the scene, else at the scene's median depth", type=float,
        metavar="M"))  # fmt: skip
    # the item's layout
    frame_offsets: tuple[int, ...] | None = None
    depth_unit: str | None = field(default=None, metadata=flag(
        "leave the replaced cameras' depth-map features (observation.images.<camera>_depth) as recorded instead of "
        "rendering them at the new pose (default: rendered)", flag="--keep-depth-maps", action="store_const",
        const="keep"))  # fmt: skip
    report: bool = False
    # how a view is rendered
    backend: str = field(default="fast", metadata=flag("render backend used in the workers"))
    render_options: dict = field(default_factory=dict)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fill_holes: bool = field(default=True, metadata=flag(
        "paint pixels no source camera saw black instead of filling them", flag="--no-fill-holes",
        action="store_false"))  # fmt: skip
    render_in: str = field(default="auto", metadata=flag(
        "worker: render in the dataloader workers; batch: render each batch on the training device after "
        "collation; auto: batch when training on CUDA", choices=RENDER_IN))  # fmt: skip
    render_scale: float = field(default=1.0, metadata=flag(
        "render the augmented views at this fraction of the frame size, then resize them to it: about scale^2 of "
        "the render time, e.g. 0.5 for 640x480 frames that the policy shrinks to 320x240 "
        "(benchmarks/render_scale.py)"))  # fmt: skip

    def __post_init__(self) -> None:
        self.cameras = distinct_cameras(self.cameras, "GenSplatConfig.cameras")
        self.replace = distinct_cameras(self.cameras if self.replace is None else self.replace, "GenSplatConfig.replace")
        if not self.cameras:
            raise ValueError("GenSplatConfig.cameras: need at least one external camera")
        if self.pivot_depth is not None and not 0 < self.pivot_depth <= MAX_PIVOT_DEPTH_M:
            raise ValueError(f"GenSplatConfig.pivot_depth: a positive distance in metres, at most {MAX_PIVOT_DEPTH_M:g}, "
                             f"got {self.pivot_depth}")  # fmt: skip
        unknown = [c for c in self.replace if c not in self.cameras]
        if unknown:
            raise ValueError(f"GenSplatConfig.replace: {unknown} are not reconstructed cameras {self.cameras}")
        if not 0 <= self.probability <= 1:
            raise ValueError(f"GenSplatConfig.probability must be in [0, 1], got {self.probability}")
        self.views_per_source = _integer("GenSplatConfig.views_per_source", self.views_per_source)
        if not 1 <= self.views_per_source <= MAX_VIEWS_PER_SOURCE:
            raise ValueError(f"GenSplatConfig.views_per_source must be in 1..{MAX_VIEWS_PER_SOURCE}, "
                             f"got {self.views_per_source}")  # fmt: skip
        if self.backend not in (*BACKENDS, "auto"):
            raise ValueError(f"GenSplatConfig.backend: unknown {self.backend!r}; available {sorted(BACKENDS)} "
                             "or 'auto'")
        if not 0 < self.render_scale <= 1:
            raise ValueError(f"GenSplatConfig.render_scale must be in (0, 1], got {self.render_scale}")
        if self.render_in not in RENDER_IN:
            raise ValueError(f"GenSplatConfig.render_in must be one of {RENDER_IN}, got {self.render_in!r}")
        self.perturbations()  # checks the sampler's settings
        shifts = {"shift_m": abs(self.shift_m), "level mu_m": max(map(abs, get_range(self.level).mu_m))}
        for name, value in shifts.items():
            if value > MAX_SHIFT_M:
                raise ValueError(f"GenSplatConfig.{name}: a camera moves at most {MAX_SHIFT_M:g} m, got {value:g}")
        self.focal_scale = tuple(float(v) for v in self.focal_scale)
        if self.depth_unit not in DEPTH_UNITS:
            raise ValueError(f"GenSplatConfig.depth_unit must be one of {tuple(DEPTH_UNITS)}, got {self.depth_unit!r}")

    def perturbations(self):
        """The perturbation sampler these settings describe (:func:`.perturbation.make_sampler`)."""
        return make_sampler(self.sampler, self.level, self.mode, self.seed, self.tilt_deg, self.arc_deg,
                            self.shift_m, self.focal_scale)  # fmt: skip

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


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """Add ``gensplat cache``'s flag for every :class:`GenSplatConfig` field that has one
    (:func:`.core.config_flags.flag`), with the field's default and type."""
    add_flags(parser, GenSplatConfig)


def config_from_arguments(args: argparse.Namespace, **fixed) -> GenSplatConfig:
    """The :class:`GenSplatConfig` of the flags :func:`add_config_arguments` added, parsed into
    ``args``, and the ``fixed`` fields (e.g. the cameras of the dataset)."""
    return config_from_flags(args, GenSplatConfig, **fixed)
