"""Camera calibration estimated from a dataset's own frames (``gensplat calibrate estimate``).

For static external cameras (:func:`estimate_rig`; docs/calibration.md):

1. at each sampled timestep every other camera is matched to the first (the reference): affine
   SIFT features (OpenCV), Lowe's ratio test both ways, a fundamental-matrix RANSAC (needs no
   intrinsics), and with depth only pixels whose depth is valid and smooth around them;
2. the cameras are static, so the matches of all timesteps are pooled. With depth, the focal
   lengths of both cameras and their metric pose: a grid over the focal lengths scored by
   3-point rigid fits of the back-projected matches (a wrong focal length bends the points, so
   no rigid motion fits them), then Levenberg-Marquardt on the reprojection errors in both
   images (Huber-weighted). Without depth, given focal lengths: the essential matrix (RANSAC),
   its inliers triangulated, and the scale from one distance the user gives or from a metric
   geometry model's depth at the matches; the focal lengths themselves can come from such a
   model (:func:`predict_cameras`: its median over the timesteps);
3. groups of timesteps (episodes) are estimated apart; their deviation from the pooled
   estimate is the spread, kept as the confidence of each camera;
4. the world frame is levelled on the table: the dominant plane seen from below the cameras'
   image-up direction gives world +z, world +x points from the scene towards the cameras
   (horizontally), and the origin is the table point below the pivot, so the perturbation
   protocol's rotations about world X and Y tilt the cameras as in a calibrated rig.

Assumptions, stated where the estimate is reported: square pixels, the principal point at the
image centre unless given (``principal_points``: cropped images move it), no lens distortion,
cameras static over the sampled frames.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from ..core.cameras import pivot_point
from ..core.config_flags import flag, real_number, whole_number

#: horizontal fields of view searched for a camera's focal length, degrees
FOV_RANGE_DEG = (15.0, 150.0)
#: fewest feature matches a camera pair's estimate rests on
MIN_MATCHES = 30
#: largest standard deviation of a log focal length the depth-based fit may leave: beyond it the
#: views cannot tell the focal length from the distance (a rectified stereo pair's fit; the
#: figures: docs/calibration.md, "Limits")
FOCAL_SD_MAX = 0.01
#: the distances (m) ``baseline_m`` and ``table_m`` may give: a millimetre to 100 m
DISTANCE_RANGE_M = (1e-3, 100.0)


def pixel_point(text: str) -> tuple[float, float]:
    """``CX,CY`` -> (cx, cy), the type of ``--principal-point`` (checked against the image where
    it is used: :func:`check_principal_points`)."""
    try:
        cx, cy = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected CX,CY in pixels (e.g. 311.7,255.4), got {text!r}") from None
    return cx, cy


@dataclass(frozen=True)
class EstimateConfig:
    """What the calibration estimate is given (``gensplat calibrate estimate``'s options; the
    intrinsics flags also ``calibrate from-features``'s).

    Attributes:
        timesteps: timesteps sampled across the episodes (at least 2).
        fov_deg: every camera's horizontal field of view in degrees, for cameras without depth or
            one camera alone; None: from depth or ``model``.
        focal_px: as ``fov_deg``, every camera's focal length in pixels.
        model: without depth, a geometry model predicts the focal lengths and, when it is metric
            and no distance is given, the scale: a checkpoint directory or hub id (a MoGe-2 folder,
            a Pi3-compatible model) or such a reconstructor; ``--model`` alone: the shipped small
            model.
        baseline_m: without depth, the distance between the first two cameras in metres (sets the
            scale).
        table_m: without depth, the distance from the first camera down to the table in metres
            (sets the scale).
        principal_point: (cx, cy) in pixels instead of the image centre (cropped images), one for
            every camera or one per camera; the image centre is (W / 2, H / 2), OpenCV's cx + 0.5.
        per_episode: cameras that move between episodes: every episode is estimated apart from
            ``timesteps`` of its own frames and gets its own poses.

    Raises ValueError naming the field and its flag for a value out of range, or for more than
    one source of the focal lengths (``fov_deg``, ``focal_px``, ``model``) or of the scale.
    """

    timesteps: int = field(default=16, metadata=flag("timesteps sampled across the episodes"))
    fov_deg: float | None = field(default=None, metadata=flag(
        "every camera's horizontal field of view in degrees (square pixels, principal point at the image centre)",
        flag="--fov", type=float, metavar="DEG", shown="none"))
    focal_px: float | None = field(default=None, metadata=flag(
        "as --fov, every camera's focal length in pixels", flag="--focal", type=float, metavar="PX", shown="none"))
    model: str | Path | Any | None = field(default=None, metadata=flag(
        "without depth: a geometry model predicts the focal lengths and, when it is metric and neither --baseline "
        "nor --table-distance is given, the scale; a checkpoint directory or hub id (a MoGe-2 folder, MIT: metric, "
        "nothing else needed; Depth Anything 3: Apache-2.0; Pi3: CC BY-NC 4.0, non-commercial), or alone the "
        "shipped small model (trained on simulated tabletops only)",
        nargs="?", const="shipped", metavar="DIR_OR_HUB_ID", shown="none"))
    baseline_m: float | None = field(default=None, metadata=flag(
        "without depth: the distance between the first two cameras, metres (sets the scale)", flag="--baseline",
        type=float, metavar="M", shown="none"))
    table_m: float | None = field(default=None, metadata=flag(
        "without depth: the distance from the first camera down to the table, metres (sets the scale)",
        flag="--table-distance", type=float, metavar="M", shown="none"))
    principal_point: tuple[tuple[float, float], ...] | None = field(default=None, metadata=flag(
        "the principal point in pixels instead of the image centre (cropped images), one for every camera or one "
        "per camera in --cameras order; the image centre is W/2,H/2 (OpenCV's cx, cy + 0.5)",
        type=pixel_point, nargs="+", metavar="CX,CY", shown="the image centres"))
    per_episode: bool = field(default=False, metadata=flag(
        "cameras that move between episodes; every episode is estimated apart from --timesteps of its own frames "
        "and gets its own poses", action="store_true"))

    def __post_init__(self):
        if not whole_number(self.timesteps) or self.timesteps < 2:
            raise ValueError(f"EstimateConfig.timesteps (--timesteps) must be a whole number >= 2, got {self.timesteps!r}")
        for name, option, top in (("fov_deg", "--fov", 180.0), ("focal_px", "--focal", math.inf)):
            value = getattr(self, name)
            if value is not None and not (real_number(value) and 0 < value < top):
                below = " below 180 degrees" if top < math.inf else ""
                raise ValueError(f"EstimateConfig.{name} ({option}) must be a positive number{below}, got {value!r}")
        low, high = DISTANCE_RANGE_M
        for name, option in (("baseline_m", "--baseline"), ("table_m", "--table-distance")):
            value = getattr(self, name)
            if value is not None and not (real_number(value) and low <= value <= high):
                raise ValueError(f"EstimateConfig.{name} ({option}) is a distance in metres between a camera and "
                                 f"another camera or the table: {low:g} to {high:g} m, got {value!r}")  # fmt: skip
        if sum(v is not None for v in (self.fov_deg, self.focal_px, self.model)) > 1:
            raise ValueError("EstimateConfig: give one of fov_deg (--fov), focal_px (--focal) and model (--model)")
        if self.baseline_m is not None and self.table_m is not None:
            raise ValueError("EstimateConfig: give one of baseline_m (--baseline) and table_m (--table-distance)")
        if self.principal_point is not None:
            points = self.principal_point
            pairs = isinstance(points, (list, tuple)) and len(points) > 0 and all(
                isinstance(p, (list, tuple)) and len(p) == 2 and all(map(real_number, p)) for p in points)  # fmt: skip
            if not pairs:
                raise ValueError("EstimateConfig.principal_point (--principal-point) must be one or more (cx, cy) "
                                 f"pairs of numbers in pixels, got {points!r}")  # fmt: skip
            object.__setattr__(self, "principal_point", tuple((float(cx), float(cy)) for cx, cy in points))



@dataclass
class Matches:
    """Correspondences between a camera ``a`` and a camera ``b`` at one timestep: pixel
    coordinates ``uv_a``, ``uv_b`` (M, 2) (pixel centres at +0.5) and depths ``z_a``, ``z_b`` (M,)."""

    uv_a: torch.Tensor
    z_a: torch.Tensor
    uv_b: torch.Tensor
    z_b: torch.Tensor

    def __len__(self) -> int:
        return len(self.z_a)

    def subset(self, keep: torch.Tensor) -> Matches:
        return Matches(self.uv_a[keep], self.z_a[keep], self.uv_b[keep], self.z_b[keep])

    @staticmethod
    def cat(parts: list[Matches]) -> Matches:
        return Matches(*(torch.cat([getattr(p, k) for p in parts]) for k in ("uv_a", "z_a", "uv_b", "z_b")))


@dataclass
class PairEstimate:
    """Focal lengths of cameras a and b (pixels) and the rigid transform ``b_from_a`` (4, 4)
    mapping a's camera frame into b's (x_b = R x_a + t, metres); ``rms_px``: RMS reprojection
    error of the inliers; ``matches``: how many were used; ``focal_sd``: the larger standard
    deviation of the two log focal lengths the fit leaves (large where the views cannot tell
    the focal length from the distance, e.g. parallel cameras that only translate)."""

    focal_a: float
    focal_b: float
    b_from_a: torch.Tensor
    rms_px: float
    matches: int
    focal_sd: float = 0.0


@dataclass
class RigEstimate:
    """Estimated cameras in the levelled world frame: ``K`` (V, 3, 3), ``c2w`` (V, 4, 4)
    (OpenCV axes), per camera the spread of the per-episode estimates around the pooled one
    (``focal_spread``: relative; ``rotation_spread_deg``; ``center_spread_m``: of its centre
    seen from the reference camera; NaN where given, not estimated), how many timesteps and
    matches it rests on, and what makes it metric (``scale``); ``sizes``: (width, height) per
    camera; ``principal_given``: whether the principal points were given, not assumed at the
    image centres; ``model``: the geometry model that predicted the focal lengths (its
    ``source`` and ``licence``), None for none; ``episodes``: for cameras that move between
    episodes, each episode's (V, 4, 4) poses (``c2w`` is then the first episode's), else None."""

    names: tuple[str, ...]
    K: torch.Tensor
    c2w: torch.Tensor
    focal_spread: list[float]
    rotation_spread_deg: list[float]
    center_spread_m: list[float]
    timesteps: list[int]
    matches: list[int]
    rms_px: list[float]
    sizes: list[tuple[int, int]]
    levelled: bool = True
    scale: str = "metric, from the dataset's depth"
    principal_given: bool = False
    model: dict | None = None
    episodes: dict[int, torch.Tensor] | None = None


#: a geometry model's focal lengths of one camera may deviate from their median over the sampled
#: timesteps by this much (the median relative deviation) before the estimate refuses them
MAX_FOCAL_SPREAD = 0.2


@dataclass
class ModelPrediction:
    """What a geometry model predicts of the sampled timesteps (:func:`predict_cameras`).

    Attributes:
        focals: per camera, its focal length in pixels at its image's size: the median over
            the timesteps.
        focal_spread: per camera, the median relative deviation of the timesteps' focal lengths
            from it.
        depths: per timestep, ``{name: (H, W) float32}`` the model's depth in the model's
            units at the camera's image size, inside the central square it saw, 0 elsewhere.
    """

    focals: list[float]
    focal_spread: list[float]
    depths: list[dict[str, np.ndarray]]


def predict_cameras(model, names: tuple[str, ...], timesteps: list[dict]) -> ModelPrediction:
    """The focal lengths and depth ``model`` (a :class:`.geometry.GeometryReconstructor`, or a
    single-image one such as :class:`.geometry.MonocularReconstructor`, run on each camera alone)
    predicts for cameras ``names`` at each of ``timesteps`` (``{name: (image (H, W, 3) uint8,
    ...)}``, as :func:`estimate_rig` takes them). The model sees the central square of every
    image (the aspect the shipped model was trained at; a crop keeps the focal length in
    pixels), all cameras of a timestep in one pass, uncalibrated; the principal point is taken
    at the image centre. Raises ValueError where its cameras are unusable (non-finite), it
    predicts no depth for a camera, or a camera's focal lengths spread wider than
    :data:`MAX_FOCAL_SPREAD` over the timesteps."""
    import torch.nn.functional as F

    sides = [min(timesteps[0][n][0].shape[:2]) for n in names]
    focals, depths = [], []
    for step in timesteps:
        crops = []
        for n, side in zip(names, sides):
            image = torch.from_numpy(_central_square(step[n][0])).permute(2, 0, 1).float() / 255
            crops.append(F.interpolate(image[None], size=(min(sides),) * 2, mode="bilinear", antialias=True,
                                       align_corners=False)[0])  # fmt: skip
        try:
            out = _predict(model, torch.stack(crops).clamp(0, 1))
        except ValueError as e:  # e.g. non-finite cameras
            raise ValueError(f"the geometry model's prediction of cameras {list(names)} is unusable ({e}): check "
                             "its weights and the images") from e  # fmt: skip
        scale = torch.tensor(sides, dtype=torch.float64) / out.cameras.width
        focals.append(out.cameras.K[:, 0, 0].double() * scale)
        step_depth = {}
        for i, (n, side) in enumerate(zip(names, sides)):
            full = np.zeros(step[n][0].shape[:2], dtype=np.float32)
            crop = F.interpolate(out.depths[i : i + 1].float(), size=(side, side), mode="nearest")[0, 0]
            _central_square(full)[...] = crop.numpy()
            step_depth[n] = full
        depths.append(step_depth)
    focals = torch.stack(focals)  # (T, V)
    empty = [n for n in names if not any((d[n] > 0).any() for d in depths)]
    if empty:
        raise ValueError(f"camera(s) {empty}: the geometry model predicted no valid depth at any sampled timestep: "
                         "check its weights and the images")  # fmt: skip
    median = focals.median(0).values
    spread = (focals / median - 1).abs().median(0).values
    wide = [f"{n} ({float(s):.0%})" for n, s in zip(names, spread) if not float(s) <= MAX_FOCAL_SPREAD]
    if wide:
        raise ValueError(f"the geometry model's focal lengths disagree across the sampled timesteps: camera(s) "
                         f"{', '.join(wide)} deviate from their median by more than {MAX_FOCAL_SPREAD:.0%} (the "
                         "median deviation): give the field of view (--fov) or the focal length (--focal)")  # fmt: skip
    return ModelPrediction(median.tolist(), spread.tolist(), depths)


def _predict(model, crops: torch.Tensor):
    """``model.predict_depth`` of one timestep's (V, 3, S, S) crops, uncalibrated: all at once, or
    one at a time for a single-image model (``model.single_image``, e.g. MoGe-2's), whose views
    share nothing."""
    from ..core.cameras import Cameras
    from ..core.views import Views

    if not getattr(model, "single_image", False):
        return model.predict_depth(Views(crops, None))
    outs = [model.predict_depth(Views(crop[None], None)) for crop in crops]
    first = outs[0].cameras
    cameras = Cameras(torch.cat([o.cameras.K for o in outs]), torch.cat([o.cameras.c2w for o in outs]), first.width,
                      first.height)  # fmt: skip
    return Views(torch.cat([o.images for o in outs]), cameras, torch.cat([o.depths for o in outs]))


def _central_square(image: np.ndarray) -> np.ndarray:
    """The central square (S, S, ...) view of an (H, W, ...) array, S = min(H, W)."""
    h, w = image.shape[:2]
    s = min(h, w)
    return image[(h - s) // 2 : (h - s) // 2 + s, (w - s) // 2 : (w - s) // 2 + s]


def match_pair(image_a: np.ndarray, image_b: np.ndarray, depth_a: np.ndarray | None = None,
               depth_b: np.ndarray | None = None) -> Matches:
    """Feature matches between two images of one timestep; with depth, only depth-valid ones.

    Args:
        image_a, image_b: (H, W, 3) uint8 RGB (sizes may differ).
        depth_a, depth_b: (H, W) metric depth of each, 0 (or non-finite) where unknown; None
            for none (the matches' depths are then NaN).
    """
    import cv2

    detector = cv2.AffineFeature_create(cv2.SIFT_create(nfeatures=1500, contrastThreshold=0.01), maxTilt=3,
                                        minTilt=0, tiltStep=2, rotateStepBase=90)  # at most 1500 per simulated view
    found = [detector.detectAndCompute(cv2.cvtColor(im, cv2.COLOR_RGB2GRAY), None) for im in (image_a, image_b)]
    (kp_a, des_a), (kp_b, des_b) = found
    if des_a is None or des_b is None or len(kp_a) < 8 or len(kp_b) < 8:
        return _no_matches()
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    forward = _ratio_test(matcher.knnMatch(des_a, des_b, k=2))
    backward = {(m.trainIdx, m.queryIdx) for m in _ratio_test(matcher.knnMatch(des_b, des_a, k=2))}
    pairs = [(m.queryIdx, m.trainIdx) for m in forward if (m.queryIdx, m.trainIdx) in backward]
    if len(pairs) < 8:
        return _no_matches()
    pa = np.float64([kp_a[i].pt for i, _ in pairs]) + 0.5  # OpenCV puts pixel centres at integers
    pb = np.float64([kp_b[j].pt for _, j in pairs]) + 0.5
    try:
        _, inlier = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, 1.0, 0.999, 10000)
    except cv2.error:  # MAGSAC asserts when a few (degenerate) matches admit no model: small images
        inlier = None
    if inlier is None:
        return _no_matches()
    keep = inlier.ravel().astype(bool)
    if depth_a is None or depth_b is None:
        za = zb = np.full(len(pa), np.nan)
    else:
        za, zb = _smooth_depth(depth_a, pa), _smooth_depth(depth_b, pb)
        keep &= (za > 0) & (zb > 0)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x[keep]))
    return Matches(t(pa), t(za), t(pb), t(zb))


def _ratio_test(knn, ratio: float = 0.8) -> list:
    return [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]


def _no_matches() -> Matches:
    return Matches(torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, dtype=torch.float64),
                   torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))  # fmt: skip


def _with_depth(m: Matches, depth_a: np.ndarray, depth_b: np.ndarray) -> Matches:
    """``m`` with the depths of ``depth_a``, ``depth_b`` (H, W) at its pixels where smooth
    (:func:`_smooth_depth`), NaN elsewhere; no match is dropped."""
    def z(depth: np.ndarray, uv: torch.Tensor) -> torch.Tensor:
        found = _smooth_depth(depth, uv.numpy())
        return torch.from_numpy(np.where(found > 0, found, np.nan))

    return Matches(m.uv_a, z(depth_a, m.uv_a), m.uv_b, z(depth_b, m.uv_b))


def _smooth_depth(depth: np.ndarray, uv: np.ndarray, tolerance: float = 0.02) -> np.ndarray:
    """Depth at each pixel ``uv`` (N, 2), 0 where it or a neighbour (3x3) has no depth or the
    neighbourhood spans more than ``tolerance`` of it (a depth edge: the feature may sit on
    either surface)."""
    h, w = depth.shape
    col = np.clip(np.floor(uv[:, 0]).astype(int), 1, w - 2)
    row = np.clip(np.floor(uv[:, 1]).astype(int), 1, h - 2)
    d = np.nan_to_num(depth.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    window = np.stack([d[row + dr, col + dc] for dr in (-1, 0, 1) for dc in (-1, 0, 1)], 1)
    centre = window[:, 4]
    good = (window.min(1) > 0) & (window.max(1) - window.min(1) <= tolerance * centre)
    return np.where(good, centre, 0.0)


def estimate_pair(matches: Matches, size_a: tuple[int, int], size_b: tuple[int, int],
                  init: PairEstimate | None = None, centres=None) -> PairEstimate:
    """Focal lengths and relative pose of two cameras from depth-valid ``matches``
    (``size_*``: (width, height); square pixels; ``centres``: the principal points (cx, cy) of
    a and b, default the image centres). Starts from ``init`` when given, else from a grid
    over :data:`FOV_RANGE_DEG`."""
    if len(matches) < MIN_MATCHES:
        raise ValueError(f"only {len(matches)} depth-valid matches between the cameras (need {MIN_MATCHES}): "
                         "they may see too little in common, or the frames too little texture")  # fmt: skip
    ca, cb = _centre(size_a, centres, 0), _centre(size_b, centres, 1)
    if init is None:
        fa, fb, R, t = _focal_grid(matches, ca, cb, size_a[0], size_b[0])
    else:
        fa, fb, R, t = init.focal_a, init.focal_b, init.b_from_a[:3, :3], init.b_from_a[:3, 3]
    return _refine(matches, ca, cb, fa, fb, R, t)


def _centre(size: tuple[int, int], centres=None, i: int = 0) -> torch.Tensor:
    """The principal point ``centres[i]`` (cx, cy), or without ``centres`` the image centre."""
    point = (size[0] / 2, size[1] / 2) if centres is None else centres[i]
    return torch.tensor([float(point[0]), float(point[1])], dtype=torch.float64)


def check_principal_points(names, sizes: list[tuple[int, int]], points) -> None:
    """ValueError unless each camera's given principal point (cx, cy) in ``points`` is finite
    and inside its image ``sizes`` (width, height), pixel centres at +0.5 (the image centre is
    (W / 2, H / 2)); ``points`` None (the image centres) passes."""
    if points is None:
        return
    if len(points) != len(names):
        raise ValueError(f"--principal-point: {len(points)} principal points for {len(names)} cameras {list(names)}: "
                         "give one CX,CY for every camera, or one per camera")  # fmt: skip
    for name, (w, h), point in zip(names, sizes, points):
        cx, cy = (float(v) for v in point)
        if not (math.isfinite(cx) and math.isfinite(cy) and 0 < cx < w and 0 < cy < h):
            raise ValueError(f"--principal-point of camera {name!r}: ({cx}, {cy}) must be finite and inside its "
                             f"{w}x{h} image (0 < cx < {w}, 0 < cy < {h}; the centre is ({w / 2}, {h / 2}))")  # fmt: skip


def _lift(uv: torch.Tensor, z: torch.Tensor, f, c: torch.Tensor) -> torch.Tensor:
    """(..., M, 3) camera-frame points of pixels ``uv`` (M, 2) at depth ``z`` for focal ``f``
    (a number, or (...) focal lengths)."""
    f = torch.as_tensor(f, dtype=uv.dtype)[..., None]
    xy = (uv - c) * z[:, None]
    return torch.stack([xy[:, 0] / f, xy[:, 1] / f, z.expand(f.shape[:-1] + z.shape)], -1)


def _kabsch(x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation (..., 3, 3) and translation (..., 3) minimising |R x + t - y|^2 over points (..., M, 3)."""
    mx, my = x.mean(-2, keepdim=True), y.mean(-2, keepdim=True)
    U, _, Vh = torch.linalg.svd((x - mx).transpose(-1, -2) @ (y - my))
    d = torch.sign(torch.linalg.det(Vh.transpose(-1, -2) @ U.transpose(-1, -2)))
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    R = Vh.transpose(-1, -2) @ D @ U.transpose(-1, -2)
    return R, (my - mx @ R.transpose(-1, -2))[..., 0, :]


def _focal_grid(matches: Matches, ca, cb, width_a: int, width_b: int, steps: int = 16, hypotheses: int = 96,
                max_points: int = 1000, tolerance: float = 0.02):
    """Focal lengths and a rigid transform from log grids over :data:`FOV_RANGE_DEG`: for every
    pair of focal lengths, 3-point rigid fits of the back-projected matches (the same random
    triples for every pair) are scored by how many matches they bring within ``tolerance`` of
    their depth; the pair and fit with most such matches win (RANSAC over the grid). A
    ``steps`` x ``steps`` grid over the whole range, then one as fine around its winner."""
    g = torch.Generator().manual_seed(0)
    m = matches.subset(torch.randperm(len(matches), generator=g)[:max_points])
    triples = torch.randint(len(m), (hypotheses, 3), generator=g)
    tan = torch.tan(torch.deg2rad(torch.tensor(FOV_RANGE_DEG, dtype=torch.float64)) / 2)
    log_a, log_b = (torch.log(w / 2 / tan[1]) for w in (width_a, width_b))  # widest view first
    span = float(torch.log(tan[1] / tan[0]))
    ranges = ((log_a, log_a + span), (log_b, log_b + span))
    for _ in range(2):
        fa, fb = (torch.exp(torch.linspace(lo, hi, steps, dtype=torch.float64)) for lo, hi in ranges)
        i, j, R, t = _best_fit(m, triples, fa, fb, ca, cb, tolerance)
        half = span / (steps - 1)  # the next grid spans one step either side of the winner
        ranges = ((torch.log(fa[i]) - half, torch.log(fa[i]) + half), (torch.log(fb[j]) - half, torch.log(fb[j]) + half))
        span = 2 * half
    return float(fa[i]), float(fb[j]), R, t


def _best_fit(m: Matches, triples: torch.Tensor, fa: torch.Tensor, fb: torch.Tensor, ca, cb, tolerance: float):
    """Indices into ``fa`` (G,) and ``fb`` (G,) and the rigid fit (R (3, 3), t (3,)) of the best
    3-point hypothesis over all pairs of focal lengths (see :func:`_focal_grid`)."""
    xa, xb = _lift(m.uv_a, m.z_a, fa, ca).float(), _lift(m.uv_b, m.z_b, fb, cb).float()  # (G, M, 3)
    best = (-1, None)
    for i in range(len(fa)):  # one focal of a at a time: (G, H, M) scores stay small
        sa, sb = xa[i][triples][None].expand(len(fb), -1, -1, -1), xb[:, triples]  # (G, H, 3, 3)
        R, t = _kabsch(sa, sb)
        moved = torch.einsum("ghij,mj->ghmi", R, xa[i]) + t[:, :, None]
        count = ((moved - xb[:, None]).norm(dim=-1) <= tolerance * m.z_b.float()).sum(-1)  # (G, H)
        k = int(count.argmax())
        if int(count.view(-1)[k]) > best[0]:
            j, h = divmod(k, triples.shape[0])
            best = (int(count.view(-1)[k]), (i, j, R[j, h].double(), t[j, h].double()))
    return best[1]


def _refine(m: Matches, ca, cb, fa: float, fb: float, R: torch.Tensor, t: torch.Tensor,
            iterations: int = 30) -> PairEstimate:
    """Levenberg-Marquardt over (log fa, log fb, rotation vector, t) on the reprojection errors
    of a's points in b and b's points in a, with Huber weights (1.5 px); the final rms is over
    matches within 3 px."""
    p = torch.cat([torch.tensor([math.log(fa), math.log(fb)], dtype=torch.float64),
                   rotation_matrix_to_axis_angle(R[None].double())[0], t.double()])  # fmt: skip

    def residuals(p):
        R = axis_angle_to_rotation_matrix(p[None, 2:5])[0]
        return _reprojection(m, ca, cb, torch.exp(p[0]), torch.exp(p[1]), R, p[5:8])

    p = _least_squares(residuals, p, iterations)
    r = residuals(p).norm(dim=-1)
    inlier = r <= 3.0
    b_from_a = torch.eye(4, dtype=torch.float64)
    b_from_a[:3, :3], b_from_a[:3, 3] = axis_angle_to_rotation_matrix(p[None, 2:5])[0], p[5:8]
    rms = float(r[inlier].square().mean().sqrt()) if inlier.any() else float("inf")
    J = torch.func.jacfwd(lambda q: residuals(q)[inlier].reshape(-1))(p)
    cov = torch.linalg.pinv(J.T @ J) * rms**2  # Gauss-Newton covariance of the parameters
    sd = float(cov.diagonal()[:2].clamp_min(0).sqrt().max())
    return PairEstimate(float(torch.exp(p[0])), float(torch.exp(p[1])), b_from_a, rms, int(inlier.sum()) // 2, sd)


def _least_squares(residuals, p: torch.Tensor, iterations: int = 30, huber: float = 1.5) -> torch.Tensor:
    """Levenberg-Marquardt: the parameters (P,) near ``p`` minimising the Huber-weighted
    (``huber`` pixels, per row) squares of ``residuals(p)`` (M, k)."""
    damping = 1e-3
    for _ in range(iterations):
        r = residuals(p)
        w = (huber / r.norm(dim=-1).clamp_min(huber)).repeat_interleave(r.shape[-1])  # per row, per coordinate
        J = torch.func.jacfwd(lambda q: residuals(q).reshape(-1))(p)
        rf = r.reshape(-1)
        A, g = J.T @ (J * w[:, None]), J.T @ (w * rf)
        cost = (w * rf**2).sum()
        for _ in range(8):
            step = torch.linalg.solve(A + damping * torch.diag(A.diagonal().clamp_min(1e-9)), -g)
            if (w * residuals(p + step).reshape(-1) ** 2).sum() < cost:
                break
            damping *= 10
        else:
            break
        p, damping = p + step, max(damping / 10, 1e-9)
        if step.abs().max() < 1e-10:
            break
    return p


def rotation_angle_deg(R: torch.Tensor) -> torch.Tensor:
    """Angle (...) in degrees of rotations (..., 3, 3)."""
    cos = ((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)
    return torch.rad2deg(torch.arccos(cos))


def spread(estimates: list[PairEstimate], final: PairEstimate) -> tuple[float, float, float, float]:
    """Median deviation of partial estimates from ``final``: focal a and b (relative), rotation
    (degrees) and b's centre seen from a (metres); NaN without partial estimates."""
    if not estimates:
        return (math.nan,) * 4
    centre = lambda T: -T[:3, :3].T @ T[:3, 3]  # b's centre in a's frame
    Rf = final.b_from_a[:3, :3]
    return (float(torch.tensor([abs(e.focal_a / final.focal_a - 1) for e in estimates]).median()),
            float(torch.tensor([abs(e.focal_b / final.focal_b - 1) for e in estimates]).median()),
            float(rotation_angle_deg(torch.stack([e.b_from_a[:3, :3] @ Rf.T for e in estimates])).median()),
            float(torch.stack([(centre(e.b_from_a) - centre(final.b_from_a)).norm() for e in estimates]).median()))  # fmt: skip


def estimate_rig(names: tuple[str, ...], sizes: list[tuple[int, int]], timesteps: list[dict],
                 groups: list | None = None, progress: bool = False, focals: list[float] | None = None,
                 scale: tuple[str, float] | None = None, principal_points: list | None = None,
                 predicted: list[dict] | None = None) -> RigEstimate:
    """Estimate static cameras ``names`` (the first is the reference) from ``timesteps``, each
    ``{name: (image (H, W, 3) uint8, depth (H, W) metres or None)}``; ``sizes``: (width, height)
    per camera. What is estimated depends on what is given:

    * every camera with depth, two or more cameras: focal lengths and poses, metric;
    * ``focals`` given (pixels per camera): poses from the essential matrix, metric by the
      depth where every camera has it, else (two cameras) by ``scale``: ``("baseline",
      metres)`` between cameras 0 and 1, or ``("table", metres)`` from camera 0's centre down
      to the table plane;
    * one camera with depth and its focal length in ``focals``: its pose levelled on the table.

    ``predicted``: without the dataset's depth, a metric geometry model's depth per timestep
    (``{name: (H, W) metres, 0 where none}``, :attr:`ModelPrediction.depths`) in its place
    where ``scale`` is not given: each pair is scaled by the median ratio of the model's depth
    to the triangulated depth at the matches, and one camera is levelled on it.

    ``principal_points``: (cx, cy) per camera in pixels (pixel centres at +0.5), used instead
    of the image centres everywhere (cropped images move them; a wrong one biases the pose and
    the depth-derived scale).

    The cameras are static, so the matches of all timesteps are pooled into one estimate per
    camera pair; ``groups`` (a label per timestep, e.g. its episode; default: four interleaved
    groups) are estimated apart from it too, and their deviation from it is the spread.
    Raises ValueError naming what is missing or why a camera cannot be estimated."""
    check_principal_points(names, sizes, principal_points)
    centres = principal_points or [(w / 2, h / 2) for w, h in sizes]
    timesteps, depth, by_model = _depth_source(names, timesteps, focals, scale, predicted)
    groups = list(groups) if groups is not None else [i % 4 for i in range(len(timesteps))]
    pairs = []
    for k in range(1, len(names)):
        found = _matched(timesteps, names[0], names[k], predicted if by_model else None, depth, progress)
        if focals:
            pairs.append(_rgb_pair(found, groups, _K(focals[0], sizes[0], centres[0]),
                                   _K(focals[k], sizes[k], centres[k])))
        else:
            pairs.append(_depth_pair(found, groups, sizes[0], sizes[k], names[0], names[k],
                                     (centres[0], centres[k])))  # fmt: skip
    estimated = not focals
    if estimated:
        focals = [float(torch.tensor([p.final.focal_a for p in pairs]).median())] + [p.final.focal_b for p in pairs]
    elif pairs:
        pairs = _metric_pairs(pairs, names, scale)
    K = torch.stack([_K(f, s, c) for f, s, c in zip(focals, sizes, centres)])
    c2w = _rig(pairs)
    world_from_ref, levelled = level_frame(_table_points(timesteps, names, K, c2w, pairs, depth), c2w)
    return RigEstimate(names=names, K=K, c2w=world_from_ref @ c2w, sizes=[tuple(s) for s in sizes], levelled=levelled,
                       scale=_scale_source(depth, by_model, scale), principal_given=principal_points is not None,
                       **_camera_statistics(pairs, estimated, len(names), len(timesteps)))  # fmt: skip


def _depth_source(names: tuple[str, ...], timesteps: list[dict], focals: list[float] | None,
                  scale: tuple[str, float] | None, predicted: list[dict] | None) -> tuple[list[dict], bool, bool]:
    """(timesteps, depth, by_model): whether the estimate rests on depth, and whether on a geometry
    model's (``predicted``, where the dataset has none), which for one camera takes the dataset's
    place in ``timesteps``; ValueError where what is given does not determine the cameras."""
    depth = all(step[n][1] is not None for step in timesteps for n in names)
    by_model = predicted is not None and not depth
    if by_model and (scale is not None or len(predicted) != len(timesteps)):
        raise ValueError("a geometry model's depth gives the scale where no distance is given: "
                         f"{len(predicted)} depth maps for {len(timesteps)} timesteps, scale {scale}")  # fmt: skip
    if by_model and len(names) == 1:  # levelled on the model's depth as on the dataset's
        timesteps = [{n: (step[n][0], p[n]) for n in names} for step, p in zip(timesteps, predicted)]
        depth = True
    if len(names) == 1 and not (depth and focals):
        raise ValueError("one external camera: its focal length is not observable from its own frames; give it "
                         "(--fov or --focal) or a geometry model (--model), and the camera needs depth (or the "
                         "model's) to find the table")  # fmt: skip
    if not depth and (not focals or (scale is None and not by_model)):
        raise ValueError("without depth the calibration needs the cameras' focal length (--fov or --focal) and "
                         "one distance for the scale (--baseline or --table-distance), or a geometry model "
                         "(--model) for either")  # fmt: skip
    if depth and scale is not None:
        raise ValueError("the cameras' depth gives the scale: leave out --baseline and --table-distance")
    if not depth and len(names) > 2 and not by_model:
        raise ValueError("without depth, one distance scales one camera pair: estimate two cameras at a time")
    return timesteps, depth, by_model


def _matched(timesteps: list[dict], a: str, b: str, predicted: list[dict] | None, depth: bool,
             progress: bool) -> list[Matches]:
    """Every timestep's feature matches of cameras ``a`` and ``b`` (:func:`match_pair`; with a
    geometry model's depth, ``predicted``, their depth the model's); ValueError for fewer than
    :data:`MIN_MATCHES` in all."""
    from tqdm.auto import tqdm

    steps = tqdm(timesteps, desc=f"matching {a}-{b}", unit="timestep", disable=not progress)
    found = [match_pair(s[a][0], s[b][0], s[a][1], s[b][1]) for s in steps]
    if predicted is not None:
        found = [_with_depth(m, p[a], p[b]) for m, p in zip(found, predicted)]
    if len(Matches.cat(found)) < MIN_MATCHES:
        raise ValueError(f"cameras {a!r} and {b!r}: {len(Matches.cat(found))} feature matches "
                         f"{'with depth ' if depth else ''}in {len(timesteps)} sampled timesteps (need "
                         f"{MIN_MATCHES}): the cameras may see too little in common, or the frames too little "
                         "texture")  # fmt: skip
    return found


def _metric_pairs(pairs: list[_Pair], names: tuple[str, ...], scale: tuple[str, float] | None) -> list[_Pair]:
    """Essential-matrix ``pairs`` (unit translations) made metric: all by the one distance
    ``scale`` gives, else each by the depth at its matches."""
    unit = _unit_distance(scale[0], torch.cat([p.points for p in pairs]), _rig(pairs)) if scale else None
    lost = [names[k + 1] for k, p in enumerate(pairs) if unit is None and not p.depth_scale > 0]
    if lost:
        raise ValueError(f"camera(s) {lost}: no triangulated match has depth to scale it by (the model's depth "
                         "covers the central square of each image): give --baseline or --table-distance")  # fmt: skip
    return [p.scaled(p.depth_scale if unit is None else scale[1] / unit) for p in pairs]


def _table_points(timesteps: list[dict], names: tuple[str, ...], K: torch.Tensor, c2w: torch.Tensor,
                  pairs: list[_Pair], depth: bool) -> torch.Tensor:
    """(N, 3) points in the reference frame to find the table among: with ``depth``, the
    cameras' depth at the first four timesteps, else the pairs' triangulated points."""
    if depth:
        return _scene_points(timesteps[: min(len(timesteps), 4)], names, K, c2w)
    return torch.cat([p.points for p in pairs])


def _scale_source(depth: bool, by_model: bool, scale: tuple[str, float] | None) -> str:
    """What makes the estimate metric (:attr:`RigEstimate.scale`)."""
    given = "between the first two cameras" if scale and scale[0] == "baseline" else "from the first camera to the table"
    return ("metric, from the geometry model's depth" if by_model else "metric, from the dataset's depth" if depth
            else f"metric, from the {scale[1]} m given {given}")  # fmt: skip


def _camera_statistics(pairs: list[_Pair], estimated: bool, cameras: int, timesteps: int) -> dict:
    """Per camera, the reference first, the :class:`RigEstimate` fields that say how well it is
    estimated: its spreads (a NaN focal spread where the focal lengths were given, not
    ``estimated``), timesteps, matches and RMS reprojection error."""
    return {"focal_spread": [max(p.focal_spread[0] for p in pairs)] + [p.focal_spread[1] for p in pairs] if estimated
                            else [math.nan] * cameras,
            "rotation_spread_deg": [0.0] + [p.rotation_spread for p in pairs],
            "center_spread_m": [0.0] + [p.center_spread for p in pairs],
            "timesteps": [max([p.used for p in pairs], default=timesteps)] + [p.used for p in pairs],
            "matches": [max([p.final.matches for p in pairs], default=0)] + [p.final.matches for p in pairs],
            "rms_px": [pairs[0].final.rms_px if pairs else math.nan] + [p.final.rms_px for p in pairs]}  # fmt: skip


def _rig(pairs: list[_Pair]) -> torch.Tensor:
    """(V, 4, 4) poses in the reference camera's frame: the reference, then each pair's other camera."""
    return torch.stack([torch.eye(4, dtype=torch.float64)] + [torch.linalg.inv(p.final.b_from_a) for p in pairs])


class _Pair(NamedTuple):
    """One camera pair's estimate, its spread over the groups, how many timesteps gave matches,
    and for an essential-matrix estimate (unit translation) its triangulated points in camera
    a's frame, (N, 3), and the median ratio of their measured depth to theirs (NaN without)."""

    final: PairEstimate
    focal_spread: tuple[float, float]
    rotation_spread: float
    center_spread: float
    used: int
    points: torch.Tensor | None = None
    depth_scale: float = math.nan

    def scaled(self, s: float) -> _Pair:
        """The pair with its translation, points and centre spread multiplied by ``s``."""
        b_from_a = self.final.b_from_a.clone()
        b_from_a[:3, 3] *= s
        final = PairEstimate(self.final.focal_a, self.final.focal_b, b_from_a, self.final.rms_px, self.final.matches)
        return self._replace(final=final, points=self.points * s, center_spread=self.center_spread * s)


def _depth_pair(found: list[Matches], groups: list, size_a, size_b, name_a: str, name_b: str,
                centres=None) -> _Pair:
    """Focal lengths and metric pose of a camera pair from their depth-valid ``found`` matches
    (``centres``: their principal points, default the image centres)."""
    pooled = Matches.cat(found)
    first = estimate_pair(pooled, size_a, size_b, centres=centres)
    agreeing = _agreeing(pooled, first, size_a, size_b, centres=centres)
    if len(agreeing) < MIN_MATCHES:
        raise ValueError(f"cameras {name_a!r} and {name_b!r}: only {len(agreeing)} of {len(pooled)} feature matches "
                         "agree on one calibration: the cameras may see too little in common")  # fmt: skip
    final = estimate_pair(agreeing, size_a, size_b, first, centres)
    if final.focal_sd > FOCAL_SD_MAX:
        raise ValueError(f"cameras {name_a!r} and {name_b!r}: the views do not tell their focal lengths from their "
                         f"distance (standard deviation {final.focal_sd:.1%} of the focal length; e.g. parallel "
                         "cameras that only translate): give the field of view with --fov or --focal")  # fmt: skip
    parts = []
    for label in dict.fromkeys(groups):
        m = _agreeing(Matches.cat([f for f, g in zip(found, groups) if g == label]), final, size_a, size_b,
                      centres=centres)  # fmt: skip
        if len(m) >= MIN_MATCHES:
            parts.append(estimate_pair(m, size_a, size_b, final, centres))
    fa, fb, rot, centre = spread(parts, final)
    return _Pair(final, (fa, fb), rot, centre, sum(len(f) > 0 for f in found))


def _rgb_pair(found: list[Matches], groups: list, K_a: torch.Tensor, K_b: torch.Tensor) -> _Pair:
    """Rotation and unit-length translation of a camera pair of known intrinsics from the
    essential matrix of their pooled matches (RANSAC), its inliers triangulated; the spread
    is that of per-group essential matrices."""
    final, inliers = _essential(Matches.cat(found), K_a, K_b)
    parts = []
    for label in dict.fromkeys(groups):
        m = Matches.cat([f for f, g in zip(found, groups) if g == label])
        if len(m) >= MIN_MATCHES:
            parts.append(_essential(m, K_a, K_b)[0])
    _, _, rot, centre = spread(parts, final)
    points, front = _triangulate(inliers, K_a, K_b, final.b_from_a)
    ratio = inliers.z_a[front] / points[:, 2]
    ratio = ratio[torch.isfinite(ratio) & (ratio > 0)]
    return _Pair(final, (math.nan, math.nan), rot, centre, sum(len(f) > 0 for f in found), points,
                 float(ratio.median()) if len(ratio) else math.nan)  # fmt: skip


def _essential(m: Matches, K_a: torch.Tensor, K_b: torch.Tensor) -> tuple[PairEstimate, Matches]:
    """The pose (unit translation) of cameras with intrinsics ``K_a``, ``K_b`` from matches
    ``m``: OpenCV's essential-matrix RANSAC (1 px) and cheirality check, then
    Levenberg-Marquardt on the inliers' Sampson distances; with their RMS in pixels, and the
    inliers."""
    import cv2

    xa = ((m.uv_a - K_a[:2, 2]) / K_a[0, 0]).numpy()
    xb = ((m.uv_b - K_b[:2, 2]) / K_b[0, 0]).numpy()
    threshold = 2.0 / float(K_a[0, 0] + K_b[0, 0])  # one pixel in normalised coordinates
    E, mask = cv2.findEssentialMat(xa, xb, np.eye(3), method=cv2.RANSAC, prob=0.9999, threshold=threshold)
    if E is None or E.shape != (3, 3):
        raise ValueError(f"no essential matrix fits the {len(m)} feature matches: the cameras may see too little "
                         "in common, or their focal lengths are wrong")  # fmt: skip
    _, R, t, mask = cv2.recoverPose(E, xa, xb, np.eye(3), mask=mask)
    keep = torch.from_numpy(mask.ravel() > 0)
    ha, hb = (torch.cat([torch.from_numpy(x)[keep], torch.ones(int(keep.sum()), 1, dtype=torch.float64)], 1)
              for x in (xa, xb))  # fmt: skip
    f = (float(K_a[0, 0]) + float(K_b[0, 0])) / 2

    def sampson(p):  # (M, 1) Sampson distances in pixels of the inliers under rotation vector p[:3], t p[3:]
        Rm, tv = axis_angle_to_rotation_matrix(p[None, :3])[0], p[3:] / p[3:].norm()
        tx = torch.stack([torch.stack([tv[0] * 0, -tv[2], tv[1]]), torch.stack([tv[2], tv[0] * 0, -tv[0]]),
                          torch.stack([-tv[1], tv[0], tv[0] * 0])])  # fmt: skip
        Em = tx @ Rm
        Ea, Eb = ha @ Em.T, hb @ Em
        num = (hb * Ea).sum(1)
        return (f * num / (Ea[:, :2].square().sum(1) + Eb[:, :2].square().sum(1)).sqrt().clamp_min(1e-12))[:, None]

    p = torch.cat([rotation_matrix_to_axis_angle(torch.from_numpy(R)[None])[0], torch.from_numpy(t.ravel())])
    p = _least_squares(sampson, p, huber=1.0)
    b_from_a = torch.eye(4, dtype=torch.float64)
    b_from_a[:3, :3], b_from_a[:3, 3] = axis_angle_to_rotation_matrix(p[None, :3])[0], p[3:] / p[3:].norm()
    rms = float(sampson(p).square().mean().sqrt()) if len(ha) else math.inf
    return PairEstimate(float(K_a[0, 0]), float(K_b[0, 0]), b_from_a, rms, int(keep.sum())), m.subset(keep)


def _triangulate(m: Matches, K_a: torch.Tensor, K_b: torch.Tensor,
                 b_from_a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(N, 3) points in camera a's frame of matches ``m``, those in front of both cameras, and
    which of the matches they are ((M,) bool)."""
    import cv2

    xa = ((m.uv_a - K_a[:2, 2]) / K_a[0, 0]).numpy().T
    xb = ((m.uv_b - K_b[:2, 2]) / K_b[0, 0]).numpy().T
    X = cv2.triangulatePoints(np.eye(3, 4), b_from_a[:3].numpy(), xa, xb)
    points = torch.from_numpy((X[:3] / X[3:]).T.copy())
    in_b = points @ b_from_a[:3, :3].T + b_from_a[:3, 3]
    front = (points[:, 2] > 0) & (in_b[:, 2] > 0)
    return points[front], front


def _unit_distance(kind: str, points: torch.Tensor, c2w: torch.Tensor) -> float:
    """The distance that ``scale`` gives in metres, in the units of an unscaled estimate:
    between cameras 0 and 1 (``"baseline"``) or from camera 0 down to the table (``"table"``)."""
    if kind == "baseline":
        if len(c2w) < 2:
            raise ValueError("--baseline is the distance between the first two cameras: give two cameras")
        return float((c2w[1, :3, 3] - c2w[0, :3, 3]).norm())
    world_from_ref, levelled = level_frame(points, c2w)
    if not levelled:
        raise ValueError("--table-distance: no table plane found among the matched points; give --baseline")
    return abs(float((world_from_ref @ c2w[0])[2, 3]))


def _reprojection(m: Matches, ca, cb, fa, fb, R: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """(2M, 2) pixel errors of a's matched points seen by b, then of b's seen by a, for focal
    lengths ``fa``, ``fb`` and x_b = R x_a + t."""
    xb = _lift(m.uv_a, m.z_a, fa, ca) @ R.T + t
    xa = (_lift(m.uv_b, m.z_b, fb, cb) - t) @ R
    ub = fb * xb[:, :2] / xb[:, 2:].clamp_min(1e-6) + cb - m.uv_b
    ua = fa * xa[:, :2] / xa[:, 2:].clamp_min(1e-6) + ca - m.uv_a
    return torch.cat([ub, ua], 0)


def _agreeing(m: Matches, e: PairEstimate, size_a, size_b, max_px: float = 4.0, centres=None) -> Matches:
    """The matches whose reprojection error under ``e`` is within ``max_px`` both ways
    (``centres``: the principal points, default the image centres)."""
    r = _reprojection(m, _centre(size_a, centres, 0), _centre(size_b, centres, 1), e.focal_a, e.focal_b,
                      e.b_from_a[:3, :3], e.b_from_a[:3, 3]).norm(dim=-1)  # fmt: skip
    return m.subset((r[: len(m)] <= max_px) & (r[len(m) :] <= max_px))


def _K(f: float, size: tuple[int, int], centre=None) -> torch.Tensor:
    """Square pixels of focal ``f``; the principal point ``centre`` (cx, cy), default the centre of ``size``."""
    cx, cy = _centre(size, None if centre is None else [centre]).tolist()
    return torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=torch.float64)


def _scene_points(timesteps: list[dict], names, K: torch.Tensor, c2w: torch.Tensor, per_view: int = 20000):
    """(N, 3) points of the cameras' depth in the reference frame (a random subset per view)."""
    g = torch.Generator().manual_seed(0)
    out = []
    for step in timesteps:
        for i, n in enumerate(names):
            depth = torch.as_tensor(np.nan_to_num(step[n][1].astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0))
            w = depth.shape[1]
            idx = torch.nonzero(depth.reshape(-1) > 0)[:, 0]
            idx = idx[torch.randperm(len(idx), generator=g)[:per_view]]
            uv = torch.stack([idx % w + 0.5, idx // w + 0.5], -1).double()
            cam = _lift(uv, depth.reshape(-1)[idx], float(K[i, 0, 0]), K[i, :2, 2])
            out.append(cam @ c2w[i, :3, :3].T + c2w[i, :3, 3])
    return torch.cat(out)


def level_frame(points: torch.Tensor, c2w: torch.Tensor, max_tilt_deg: float = 50.0,
                iterations: int = 400) -> tuple[torch.Tensor, bool]:
    """The (4, 4) transform into a levelled world frame, and whether a table plane was found.

    World +z is the normal of the plane (RANSAC over ``points`` (N, 3)) with most points among
    planes within ``max_tilt_deg`` of the cameras' mean image-up direction (-y), oriented
    towards the cameras; without such a plane, image-up itself. World +x is the horizontal part
    of the cameras' mean viewing direction, reversed (from the scene towards the cameras).
    The origin is the plane point below the pivot of cameras 0 and 1 (below camera 0's
    centre for one camera)."""
    up_guess = -c2w[:, :3, 1].mean(0)
    up_guess = up_guess / up_guess.norm()
    centres = c2w[:, :3, 3]
    g = torch.Generator().manual_seed(0)
    scale = points[:, 2].abs().median() if len(points) else torch.tensor(1.0)
    best, best_count = None, 0
    if len(points) >= 3:
        tri = points[torch.randint(len(points), (iterations, 3), generator=g)]
        n = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        n = n * torch.sign(n @ up_guess)[:, None]
        ok = torch.rad2deg(torch.arccos((n @ up_guess).clamp(-1, 1))) <= max_tilt_deg
        d = (points[None] - tri[:, None, 0]) @ n[..., None]  # (I, N, 1) signed distances
        counts = ((d[..., 0].abs() <= 0.005 * scale) & ok[:, None]).sum(1)
        i = int(counts.argmax())
        if ok[i] and counts[i] >= max(100, 0.05 * len(points)):
            inl = points[d[i, :, 0].abs() <= 0.005 * scale]
            mean = inl.mean(0)
            normal = torch.linalg.svd(inl - mean, full_matrices=False).Vh[-1]
            normal = normal * torch.sign((centres.mean(0) - mean) @ normal)
            best, best_count = (normal, mean), int(counts[i])
    z = best[0] if best is not None else up_guess
    forward = c2w[:, :3, 2].mean(0)
    x = -(forward - (forward @ z) * z)
    if x.norm() < 1e-6:  # cameras looking straight down: x along camera 0's image x
        x = c2w[0, :3, 0] - (c2w[0, :3, 0] @ z) * z
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    centre = pivot_point(c2w[0], c2w[1]) if len(c2w) > 1 else centres[0]
    origin = centre if best is None else centre - ((centre - best[1]) @ z) * z
    ref_from_world = torch.eye(4, dtype=torch.float64)
    ref_from_world[:3, :3] = torch.stack([x, y, z], 1)
    ref_from_world[:3, 3] = origin
    return torch.linalg.inv(ref_from_world), best_count > 0
