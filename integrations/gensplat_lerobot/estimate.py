"""Calibration of a LeRobot dataset estimated from its own frames (``gensplat calibrate estimate``):
frames sampled across episodes and time, :func:`gensplat_transforms.calibration.estimate.estimate_rig`,
the result written to ``<root>/gensplat/calibration.json`` as a given calibration would be,
with the estimate's spread beside it."""

from __future__ import annotations

import dataclasses
import math
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from gensplat_transforms.calibration.estimate import (
    EstimateConfig,
    RigEstimate,
    check_principal_points,
    estimate_rig,
    predict_cameras,
    rotation_angle_deg,
)
from gensplat_transforms.calibration.files import FOV_RANGE, stored_cameras
from gensplat_transforms.core.atomic import atomic_write_json
from gensplat_transforms.core.cameras import focal_from_fov
from gensplat_transforms.data.format import (
    CALIBRATION_FORMAT,
    IMAGE_KEY_PREFIX,
    calibration_path,
    camera_info,
    depth_path,
    distinct_cameras,
    load_depth,
)
from gensplat_transforms.data.outputs import gensplat_folder
from gensplat_transforms.geometry.base import DepthReconstructor

from .source import _is_depth_map, episode_table, read_info, video_backend

if TYPE_CHECKING:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

#: spreads of a pooled estimate beyond which the report suggests ``--per-episode`` (the static
#: simulated rig's: at most 0.8 deg and 0.6 cm)
MOVED_DEG, MOVED_M = 1.5, 0.02
#: what the estimate assumes, written beside it and printed (the principal point: see :func:`assumptions`)
ASSUMPTIONS = "square pixels, principal point at the image centre, no lens distortion, static cameras"


def assumptions(rig: RigEstimate) -> str:
    """What ``rig``'s estimate assumed: :data:`ASSUMPTIONS`, with the principal points where given."""
    if not rig.principal_given:
        return ASSUMPTIONS
    given = ", ".join(f"{n} ({float(rig.K[i, 0, 2]):g}, {float(rig.K[i, 1, 2]):g})" for i, n in enumerate(rig.names))
    return ASSUMPTIONS.replace("principal point at the image centre", f"principal point given: {given} px")


def estimate_calibration(root: str | Path, repo_id: str, cameras: tuple[str, ...] | None = None,
                         config: EstimateConfig | None = None, progress: bool = True) -> RigEstimate:
    """Estimate the external ``cameras`` (default: every colour camera whose name does not
    contain "wrist"; the first is the reference) of the dataset at ``root`` from
    ``config.timesteps`` frames spread over its episodes and write
    ``<root>/gensplat/calibration.json``. ``config``: what is given
    (:class:`~gensplat_transforms.calibration.estimate.EstimateConfig`; default: nothing).

    With metric depth registered to every camera's images (depth sidecars, or LeRobot
    depth-map features without a ``camera.depth`` sensor block), two or more cameras get their
    focal lengths (unless given) and metric poses from it. Otherwise the focal length is given
    (``fov_deg`` or ``focal_px``) and so is one distance for the scale (``baseline_m`` or
    ``table_m``), or ``model``, a geometry model's checkpoint directory or hub id
    (:class:`~gensplat_transforms.geometry.GeometryReconstructor`; a MoGe-2 folder:
    :class:`~gensplat_transforms.geometry.MonocularReconstructor`) or such a reconstructor, predicts the focal
    lengths (:func:`~gensplat_transforms.calibration.estimate.predict_cameras`) and, where it is
    metric and no distance is given, the scale (and one camera's table). One camera needs depth
    and its focal length. ``per_episode``: every episode is estimated apart
    (:func:`per_episode_rig`). Raises ValueError naming what is missing or wrong (see
    :func:`~gensplat_transforms.calibration.estimate.estimate_rig`).

    Example:
        >>> rig = estimate_calibration("data/my_set", "me/my_set", config=EstimateConfig(fov_deg=69.4,
        ...                            baseline_m=0.3))  # doctest: +SKIP
    """
    root, config = Path(root), config or EstimateConfig()
    features = read_info(root)["features"]
    names = _chosen_cameras(root, features, cameras)
    sizes = [(features[IMAGE_KEY_PREFIX + n]["shape"][1], features[IMAGE_KEY_PREFIX + n]["shape"][0]) for n in names]
    principal_point = _principal_points(names, sizes, config.principal_point)
    gensplat_folder(root)  # before minutes of matching, not after
    _check_uncalibrated(root, features, names)
    frames = _Frames.open(root, repo_id, features, names)
    scale = ("baseline", config.baseline_m) if config.baseline_m is not None else \
        ("table", config.table_m) if config.table_m is not None else None
    geometry = _geometry_for(root, names, config.model, frames.depth, scaled=scale is not None)
    estimator = _Estimator(frames, sizes, _given_focals(names, sizes, config.fov_deg, config.focal_px), scale,
                           principal_point, geometry, config.model)  # fmt: skip
    run = estimator.per_episode if config.per_episode else estimator.pooled
    rig = run(config.timesteps, progress)
    write_estimate(root, rig)
    return rig


def _chosen_cameras(root: Path, features: dict, cameras: tuple[str, ...] | None) -> tuple[str, ...]:
    """The cameras to estimate: ``cameras``, by default every colour camera whose name does not
    contain "wrist"; ValueError for none, or for one that is no colour image feature."""
    colour = [k[len(IMAGE_KEY_PREFIX) :] for k, ft in features.items()
              if k.startswith(IMAGE_KEY_PREFIX) and not _is_depth_map(ft)]  # fmt: skip
    names = distinct_cameras(cameras) if cameras else tuple(n for n in colour if "wrist" not in n)
    unknown = [n for n in names if n not in colour]
    if unknown:
        raise ValueError(f"{root}: camera(s) {unknown} are not colour image features of the dataset ({colour})")
    if not names:
        raise ValueError(f"{root}: no external camera to estimate among {colour} (choose them with --cameras)")
    return names


def _principal_points(names: tuple[str, ...], sizes: list[tuple[int, int]], given: list | None) -> list | None:
    """The ``given`` principal points, one for every camera or one per camera, as one per camera,
    checked against the images (None: the image centres)."""
    if given is not None and len(given) == 1:
        given = list(given) * len(names)
    check_principal_points(names, sizes, given)
    return given


def _check_uncalibrated(root: Path, features: dict, names: tuple[str, ...]) -> None:
    """ValueError where a camera's feature carries calibration (which GenSplat uses)."""
    calibrated = [n for n in names if "camera.intrinsics" in (features[IMAGE_KEY_PREFIX + n].get("info") or {})]
    if calibrated:
        raise ValueError(f"{root}: camera(s) {calibrated} carry calibration in their features, which GenSplat uses; "
                         "nothing to estimate")  # fmt: skip


def _geometry_for(root: Path, names: tuple[str, ...], model: str | Path | DepthReconstructor | None, depth: bool,
                  scaled: bool) -> DepthReconstructor | None:
    """The reconstructor of ``model`` (None for none); ValueError where the cameras have
    ``depth`` or where it is not metric and no distance gives the scale (``scaled``)."""
    if model is not None and depth:
        raise ValueError(f"{root}: cameras {list(names)} have depth, from which the estimate takes their focal "
                         "lengths and scale: leave out --model (it is for datasets without depth)")  # fmt: skip
    geometry = None if model is None else _geometry_model(model)
    if geometry is not None and not geometry.metric and not scaled:
        raise ValueError(f"--model {model}: its depth is up to scale (not metric): give --baseline or "
                         "--table-distance for the scale")  # fmt: skip
    return geometry


def _given_focals(names: tuple[str, ...], sizes: list[tuple[int, int]], fov_deg: float | None,
                  focal_px: float | None) -> list[float] | None:
    """Every camera's focal length in pixels from ``fov_deg`` (horizontal) or ``focal_px`` (None
    for neither); ValueError where it gives a camera a field of view no calibration holds."""
    if fov_deg is None and focal_px is None:
        return None
    focals = [focal_px or focal_from_fov(fov_deg, w) for w, _ in sizes]
    for n, f, (w, h) in zip(names, focals, sizes):
        fov = [math.degrees(2 * math.atan(side / 2 / f)) for side in (w, h)]
        if not all(FOV_RANGE[0] <= a <= FOV_RANGE[1] for a in fov):
            given = f"--fov {fov_deg:g}" if fov_deg is not None else f"--focal {focal_px:g}"
            raise ValueError(f"{given} gives camera {n!r} ({w}x{h}) a field of view of {fov[0]:.3g} x {fov[1]:.3g} "
                             f"degrees; calibrations hold {FOV_RANGE[0]:g} to {FOV_RANGE[1]:g} degrees")  # fmt: skip
    return focals


def _depth_key(name: str) -> str:
    """The LeRobot depth-map feature of camera ``name``."""
    return f"{IMAGE_KEY_PREFIX}{name}_depth"


@dataclasses.dataclass
class _Frames:
    """The frames of cameras ``names`` of the LeRobot ``dataset`` at ``root``, with their metric
    depth where every camera has depth registered to its images (``depth``)."""

    root: Path
    names: tuple[str, ...]
    dataset: LeRobotDataset
    depth: bool

    @classmethod
    def open(cls, root: Path, repo_id: str, features: dict, names: tuple[str, ...]) -> _Frames:
        """The dataset's frames; depth from depth sidecars, or from depth-map features without a
        ``camera.depth`` sensor block."""
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        dataset = LeRobotDataset(repo_id, root=root, video_backend=video_backend(), depth_output_unit="m")
        registered = [depth_path(root, n, 0).exists() or (_is_depth_map(features.get(_depth_key(n))) and
                      "camera.depth" not in (features[_depth_key(n)].get("info") or {})) for n in names]  # fmt: skip
        return cls(root, names, dataset, all(registered))

    @cached_property
    def table(self) -> dict[str, list[int]]:
        """Every episode's ``length`` and ``dataset_from_index`` (:func:`episode_table`)."""
        return episode_table(self.dataset.meta)

    def read(self, pairs: list[tuple[int, int]]) -> list[dict]:
        """The timesteps ``pairs`` (episode, frame) as :func:`estimate_rig` takes them: per camera
        (image (H, W, 3) uint8, depth (H, W) float32 metres or None)."""
        samples = []
        for episode, frame in pairs:
            item = self.dataset[int(self.table["dataset_from_index"][episode]) + frame]
            samples.append({n: self._view(item, n, episode, frame) for n in self.names})
        return samples

    def _view(self, item: dict, name: str, episode: int, frame: int) -> tuple[np.ndarray, np.ndarray | None]:
        """Camera ``name``'s image and depth in the dataset's ``item`` (``frame`` of ``episode``)."""
        image = (item[IMAGE_KEY_PREFIX + name].permute(1, 2, 0).clamp(0, 1) * 255).round().byte().numpy()
        depth = None
        if self.depth and depth_path(self.root, name, episode).exists():
            depth = load_depth(self.root, name, episode, frame)[0].numpy()
        elif self.depth and _depth_key(name) in item:
            depth = item[_depth_key(name)].reshape(image.shape[:2]).float().numpy()
        elif self.depth:
            raise ValueError(f"{self.root}: camera {name!r} has no depth for episode {episode} "
                             f"({depth_path(self.root, name, episode)} is missing)")  # fmt: skip
        return image, None if depth is None else np.asarray(depth, dtype=np.float32)


@dataclasses.dataclass
class _Estimator:
    """How the rig is estimated from ``frames``: each camera's image size (``sizes``, (width,
    height)), the given ``focals`` (pixels), ``scale`` and ``principal_point`` (None: not
    given), and the ``geometry`` reconstructor of ``model`` (None: none)."""

    frames: _Frames
    sizes: list[tuple[int, int]]
    focals: list[float] | None
    scale: tuple[str, float] | None
    principal_point: list | None
    geometry: DepthReconstructor | None
    model: str | Path | DepthReconstructor | None

    def pooled(self, timesteps: int, progress: bool) -> RigEstimate:
        """The estimate from ``timesteps`` frames spread over the episodes, its spread over the episodes."""
        pairs = sample_timesteps(self.frames.table["length"], timesteps)
        return self.estimate(pairs, [e for e, _ in pairs], progress)

    def per_episode(self, timesteps: int, progress: bool) -> RigEstimate:
        """Every episode estimated apart from ``timesteps`` of its own frames (:func:`per_episode_rig`);
        ValueError naming the episode whose estimate fails."""
        from tqdm.auto import tqdm

        lengths = self.frames.table["length"]
        rigs = {}
        for episode in tqdm(range(len(lengths)), desc="estimating", unit="episode", disable=not progress):
            sampled = sample_timesteps([int(lengths[episode])], timesteps)
            try:
                rigs[episode] = self.estimate([(episode, f) for _, f in sampled], None, False)
            except ValueError as e:
                raise ValueError(f"episode {episode}: {e}") from e
        return per_episode_rig(rigs)

    def estimate(self, pairs: list[tuple[int, int]], groups: list | None, show: bool) -> RigEstimate:
        """The estimate from the timesteps ``pairs`` (episode, frame), the spread over ``groups``
        (None: four interleaved groups); ``show``: progress bars."""
        names, samples = self.frames.names, self.frames.read(pairs)
        prediction = predict_cameras(self.geometry, names, samples) if self.geometry is not None else None
        rig = estimate_rig(names, self.sizes, samples, groups, progress=show, focals=prediction.focals if prediction
                           else self.focals, scale=self.scale, principal_points=self.principal_point,
                           predicted=prediction.depths if prediction and self.scale is None else None)  # fmt: skip
        if prediction is None:
            return rig
        return dataclasses.replace(rig, focal_spread=prediction.focal_spread, model=_model_record(self.model))


def per_episode_rig(rigs: dict[int, RigEstimate]) -> RigEstimate:
    """One estimate of cameras whose poses differ between episodes, from each episode's own
    ``rigs``: each camera's focal length the median over the episodes (its spread their median
    relative deviation from it; where given, the given one), the poses per episode
    (:attr:`RigEstimate.episodes`; ``c2w`` the first episode's), the other spreads the median
    of the episodes' own."""
    first = rigs[min(rigs)]
    f = np.stack([r.K[:, 0, 0].numpy() for r in rigs.values()])  # (E, V)
    median = np.median(f, 0)
    K = first.K.clone()
    K[:, 0, 0] = K[:, 1, 1] = torch.from_numpy(median)
    estimated = [not math.isnan(x) for x in first.focal_spread]
    focal_spread = [float(np.median(np.abs(f[:, i] / median[i] - 1))) if estimated[i] and len(rigs) > 1
                    else first.focal_spread[i] for i in range(len(first.names))]  # fmt: skip
    mid = lambda key: [float(np.median([getattr(r, key)[i] for r in rigs.values()])) for i in range(len(first.names))]
    return dataclasses.replace(first, K=K, focal_spread=focal_spread, rotation_spread_deg=mid("rotation_spread_deg"),
                               center_spread_m=mid("center_spread_m"), rms_px=mid("rms_px"),
                               matches=[sum(r.matches[i] for r in rigs.values()) for i in range(len(first.names))],
                               timesteps=[sum(r.timesteps[i] for r in rigs.values()) for i in range(len(first.names))],
                               levelled=all(r.levelled for r in rigs.values()),
                               episodes={e: r.c2w for e, r in rigs.items()})  # fmt: skip


def _geometry_model(model: str | Path | DepthReconstructor) -> DepthReconstructor:
    """The geometry reconstructor of checkpoint directory or hub id ``model`` (a MoGe-2 folder:
    the monocular reconstructor; a reconstructor as it is), with the error a user can act on
    where it cannot be loaded."""
    from gensplat_transforms.geometry import GeometryReconstructor, MonocularReconstructor
    from gensplat_transforms.geometry.model.moge import is_moge_checkpoint

    if isinstance(model, DepthReconstructor):
        return model
    try:
        return MonocularReconstructor(model) if is_moge_checkpoint(model) else GeometryReconstructor(model)
    except (OSError, ValueError, KeyError) as e:
        raise ValueError(f"--model {model}: cannot load a geometry model from it ({e})") from e


def _model_record(model: str | Path | DepthReconstructor) -> dict:
    """The geometry model an estimate used: where from, and its weights' licence (unknown for a
    reconstructor passed as an object)."""
    from gensplat_transforms.geometry.geometry import weights_licence

    if isinstance(model, DepthReconstructor):
        return {"source": f"{type(model).__name__} object", "licence": "unknown (passed as an object)"}
    return {"source": str(model), "licence": weights_licence(model)}


def sample_timesteps(lengths: list[int], count: int) -> list[tuple[int, int]]:
    """(episode, frame) pairs: up to ``count`` timesteps, from as many evenly spaced episodes
    as give at least two frames each, evenly spaced within each episode.

    Example:
        >>> sample_timesteps([10, 10, 10, 10], 4)
        [(0, 0), (0, 9), (3, 0), (3, 9)]
    """
    episodes = min(len(lengths), max(1, count // 2))
    chosen = sorted({round(i * (len(lengths) - 1) / max(episodes - 1, 1)) for i in range(episodes)})
    per = {e: min(max(1, count // len(chosen)), int(lengths[e])) for e in chosen}  # at most every frame
    return [(e, f) for e in chosen
            for f in sorted({round(k * (lengths[e] - 1) / max(per[e] - 1, 1)) for k in range(per[e])})]  # fmt: skip


def write_estimate(root: Path, rig: RigEstimate) -> Path:
    """``calibration.json`` of an estimated rig: its cameras in the stored calibration's form,
    and ``estimate``: method, scale (how it is metric), assumptions and each camera's spread."""
    spread = {n: {"focal_spread": _finite(rig.focal_spread[i]), "rotation_spread_deg": _finite(rig.rotation_spread_deg[i]),
                  "center_spread_m": _finite(rig.center_spread_m[i]), "matches": rig.matches[i],
                  "timesteps": rig.timesteps[i], "rms_px": _finite(rig.rms_px[i])}
              for i, n in enumerate(rig.names)}  # fmt: skip
    data = {"format": CALIBRATION_FORMAT,
            "cameras": {n: camera_info(rig.K[i], rig.c2w[i], "external",
                                       episodes={e: c2w[i] for e, c2w in (rig.episodes or {}).items()})
                        for i, n in enumerate(rig.names)},
            "estimate": {"method": "features+depth" if "dataset's depth" in rig.scale else
                                   "features+essential matrix" + (", focal lengths from a geometry model" if rig.model else ""),
                         "scale": rig.scale, **({"model": rig.model} if rig.model else {}),
                         "assumptions": assumptions(rig), "reference": rig.names[0], "levelled": rig.levelled,
                         "per_episode": rig.episodes is not None,
                         "cameras": spread}}  # fmt: skip
    try:  # what the readers refuse is not written, and the file in place is kept
        stored_cameras(calibration_path(root), data["cameras"], dict(zip(rig.names, rig.sizes)))
    except ValueError as e:
        raise ValueError(f"the estimate is not written ({calibration_path(root)} is kept as it is): {e}") from None
    gensplat_folder(root)
    return atomic_write_json(calibration_path(root), data)


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


def report(rig: RigEstimate) -> list[str]:
    """Lines describing an estimate for the terminal."""
    lines = []
    for i, n in enumerate(rig.names):
        f = float(rig.K[i, 0, 0])
        fov = math.degrees(2 * math.atan(rig.sizes[i][0] / 2 / f))
        given = math.isnan(rig.focal_spread[i])
        source = " (the geometry model's median)" if rig.model else ""
        line = f"{n}: focal {f:.1f} px ({fov:.1f} deg wide){source}, " + ("given" if given else
                                                                           f"spread {rig.focal_spread[i]:.2%}")  # fmt: skip
        if i:
            ref = np.linalg.inv(rig.c2w[0].numpy()) @ rig.c2w[i].numpy()
            angle = math.degrees(math.acos(np.clip((np.trace(ref[:3, :3]) - 1) / 2, -1, 1)))
            line += (f"; {np.linalg.norm(ref[:3, 3]):.3f} m and {angle:.1f} deg from {rig.names[0]}, spread "
                     f"{rig.center_spread_m[i] * 100:.1f} cm / {rig.rotation_spread_deg[i]:.2f} deg")  # fmt: skip
        if len(rig.names) > 1:
            line += f"; {rig.matches[i]} matches in {rig.timesteps[i]} timesteps, {rig.rms_px[i]:.2f} px rms"
        lines.append(line)
    level = "levelled on the table plane" if rig.levelled else "no table plane found: world z is the cameras' image up"
    lines.append(f"scale: {rig.scale}; world frame {level}; assumed: {assumptions(rig)}")
    if rig.model:
        lines.append(f"geometry model: {rig.model['source']}, weights licence {rig.model['licence']}")
    if rig.episodes is not None:
        ranges = []
        for i, n in enumerate(rig.names[1:], 1):
            rel = torch.stack([torch.linalg.inv(c2w[0]) @ c2w[i] for c2w in rig.episodes.values()])
            d, a = rel[:, :3, 3].norm(dim=-1), rotation_angle_deg(rel[:, :3, :3])
            ranges.append(f"{n} {float(d.min()):.3f}-{float(d.max()):.3f} m and {float(a.min()):.1f}-"
                          f"{float(a.max()):.1f} deg from {rig.names[0]}")  # fmt: skip
        lines.append(f"per episode ({len(rig.episodes)} episodes, each levelled on its own table)"
                     + (f": {', '.join(ranges)}" if ranges else ""))  # fmt: skip
    elif max(rig.rotation_spread_deg) > MOVED_DEG or max(rig.center_spread_m) > MOVED_M:
        lines.append(f"the episodes disagree (spread up to {max(rig.rotation_spread_deg):.1f} deg, "
                     f"{max(rig.center_spread_m) * 100:.1f} cm): if the cameras move between episodes, estimate "
                     "each episode apart with --per-episode")  # fmt: skip
    return lines
