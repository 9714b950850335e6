"""Camera calibration estimated from a dataset's own frames (``gensplat calibrate --estimate``).

For static external cameras with metric depth registered to their colour images:

1. each sampled timestep, every other camera is matched to the first (the reference): SIFT
   features (OpenCV), Lowe's ratio test both ways, a fundamental-matrix RANSAC (needs no
   intrinsics), and only pixels whose depth is valid and smooth around them;
2. per timestep and camera pair, the focal lengths of both cameras and their relative pose:
   a grid over the focal lengths scored by a rigid 3D fit of the back-projected matches
   (a wrong focal length bends the points, so no rotation fits them), then Levenberg-Marquardt
   on the reprojection errors in both images (Huber-weighted);
3. the per-timestep estimates are aggregated by their median (rotations: the one nearest all
   others), refined once on the pooled matches that agree with it, and their spread is kept
   as the confidence of each camera;
4. the world frame is levelled on the table: the dominant plane seen from below the cameras'
   image-up direction gives world +z, world +x points from the scene towards the cameras
   (horizontally), and the origin is the table point below the pivot, so the perturbation
   protocol's rotations about world X and Y tilt the cameras as in a calibrated rig.

Assumptions, stated where the estimate is reported: square pixels, the principal point at the
image centre, no lens distortion, cameras static over the sampled frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from kornia.geometry.conversions import axis_angle_to_rotation_matrix, rotation_matrix_to_axis_angle

from .perturbation import pivot_point

#: horizontal fields of view searched for a camera's focal length, degrees
FOV_RANGE_DEG = (15.0, 150.0)
#: fewest depth-valid matches a timestep must give to take part in the estimate
MIN_MATCHES = 30


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
    error of the inliers; ``matches``: how many were used."""

    focal_a: float
    focal_b: float
    b_from_a: torch.Tensor
    rms_px: float
    matches: int


@dataclass
class RigEstimate:
    """Estimated cameras in the levelled world frame: ``K`` (V, 3, 3), ``c2w`` (V, 4, 4)
    (OpenCV axes), per camera the spread of the per-timestep estimates around the final one
    (``focal_spread``: relative; ``rotation_spread_deg``; ``center_spread_m``: of its centre
    seen from the reference camera), and how many timesteps and matches it rests on."""

    names: tuple[str, ...]
    K: torch.Tensor
    c2w: torch.Tensor
    focal_spread: list[float]
    rotation_spread_deg: list[float]
    center_spread_m: list[float]
    timesteps: list[int]
    matches: list[int]
    rms_px: list[float]
    levelled: bool = True


def match_pair(image_a: np.ndarray, image_b: np.ndarray, depth_a: np.ndarray, depth_b: np.ndarray) -> Matches:
    """Depth-valid feature matches between two images of one timestep.

    Args:
        image_a, image_b: (H, W, 3) uint8 RGB (sizes may differ).
        depth_a, depth_b: (H, W) metric depth of each, 0 (or non-finite) where unknown.
    """
    import cv2

    detector = cv2.AffineFeature_create(cv2.SIFT_create(contrastThreshold=0.01), maxTilt=3, minTilt=0, tiltStep=2,
                                        rotateStepBase=90)
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
    _, inlier = cv2.findFundamentalMat(pa, pb, cv2.USAC_MAGSAC, 1.0, 0.999, 10000)
    if inlier is None:
        return _no_matches()
    keep = inlier.ravel().astype(bool)
    za, zb = _smooth_depth(depth_a, pa), _smooth_depth(depth_b, pb)
    keep &= (za > 0) & (zb > 0)
    t = lambda x: torch.from_numpy(np.ascontiguousarray(x[keep]))
    return Matches(t(pa), t(za), t(pb), t(zb))


def _ratio_test(knn, ratio: float = 0.8) -> list:
    return [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]


def _no_matches() -> Matches:
    return Matches(torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, dtype=torch.float64),
                   torch.zeros(0, 2, dtype=torch.float64), torch.zeros(0, dtype=torch.float64))  # fmt: skip


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
                  init: PairEstimate | None = None) -> PairEstimate:
    """Focal lengths and relative pose of two cameras from depth-valid ``matches``
    (``size_*``: (width, height); principal points at the image centres, square pixels).
    Starts from ``init`` when given, else from a grid over :data:`FOV_RANGE_DEG`."""
    if len(matches) < MIN_MATCHES:
        raise ValueError(f"only {len(matches)} depth-valid matches between the cameras (need {MIN_MATCHES}): "
                         "they may see too little in common, or the frames too little texture")  # fmt: skip
    ca, cb = _centre(size_a), _centre(size_b)
    if init is None:
        fa, fb, R, t = _focal_grid(matches, ca, cb, size_a[0], size_b[0])
    else:
        fa, fb, R, t = init.focal_a, init.focal_b, init.b_from_a[:3, :3], init.b_from_a[:3, 3]
    return _refine(matches, ca, cb, fa, fb, R, t)


def _centre(size: tuple[int, int]) -> torch.Tensor:
    return torch.tensor([size[0] / 2, size[1] / 2], dtype=torch.float64)


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


def _focal_grid(matches: Matches, ca, cb, width_a: int, width_b: int, steps: int = 48, hypotheses: int = 96,
                max_points: int = 2000, tolerance: float = 0.02):
    """Focal lengths and a rigid transform from a log grid over :data:`FOV_RANGE_DEG`: for every
    pair of focal lengths, 3-point rigid fits of the back-projected matches (the same random
    triples for every pair) are scored by how many matches they bring within ``tolerance`` of
    their depth; the pair and fit with most such matches win (RANSAC over the grid)."""
    g = torch.Generator().manual_seed(0)
    m = matches.subset(torch.randperm(len(matches), generator=g)[:max_points])
    tan = torch.tan(torch.deg2rad(torch.tensor(FOV_RANGE_DEG, dtype=torch.float64)) / 2)
    grid = torch.exp(torch.linspace(0, 1, steps, dtype=torch.float64) * torch.log(tan[1] / tan[0]))
    fa, fb = width_a / 2 / tan[1] * grid, width_b / 2 / tan[1] * grid  # widest view first
    xa, xb = _lift(m.uv_a, m.z_a, fa, ca).float(), _lift(m.uv_b, m.z_b, fb, cb).float()  # (G, M, 3)
    triples = torch.randint(len(m), (hypotheses, 3), generator=g)
    best = (-1, None)
    for i in range(steps):  # one focal of a at a time: (G, H, M) scores stay small
        sa, sb = xa[i][triples][None].expand(steps, -1, -1, -1), xb[:, triples]  # (G, H, 3, 3)
        R, t = _kabsch(sa, sb)
        moved = torch.einsum("ghij,mj->ghmi", R, xa[i]) + t[:, :, None]
        count = ((moved - xb[:, None]).norm(dim=-1) <= tolerance * m.z_b.float()).sum(-1)  # (G, H)
        k = int(count.argmax())
        if int(count.view(-1)[k]) > best[0]:
            j, h = divmod(k, hypotheses)
            best = (int(count.view(-1)[k]), (i, j, R[j, h].double(), t[j, h].double()))
    i, j, R, t = best[1]
    return float(fa[i]), float(fb[j]), R, t


def _refine(m: Matches, ca, cb, fa: float, fb: float, R: torch.Tensor, t: torch.Tensor,
            iterations: int = 30) -> PairEstimate:
    """Levenberg-Marquardt over (log fa, log fb, rotation vector, t) on the reprojection errors
    of a's points in b and b's points in a, with Huber weights (1.5 px); the final rms is over
    matches within 3 px."""
    p = torch.cat([torch.tensor([math.log(fa), math.log(fb)], dtype=torch.float64),
                   rotation_matrix_to_axis_angle(R[None].double())[0], t.double()])  # fmt: skip

    def residuals(p):
        fa, fb, Rm, tv = torch.exp(p[0]), torch.exp(p[1]), axis_angle_to_rotation_matrix(p[None, 2:5])[0], p[5:8]
        xb = _lift(m.uv_a, m.z_a, fa, ca) @ Rm.T + tv
        xa = (_lift(m.uv_b, m.z_b, fb, cb) - tv) @ Rm
        ub = fb * xb[:, :2] / xb[:, 2:].clamp_min(1e-6) + cb - m.uv_b
        ua = fa * xa[:, :2] / xa[:, 2:].clamp_min(1e-6) + ca - m.uv_a
        return torch.cat([ub, ua], 0)  # (2M, 2)

    damping = 1e-3
    for _ in range(iterations):
        r = residuals(p)
        w = (1.5 / r.norm(dim=-1).clamp_min(1.5)).repeat_interleave(2)  # Huber weights per match, per coordinate
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
    r = residuals(p).norm(dim=-1)
    inlier = r <= 3.0
    b_from_a = torch.eye(4, dtype=torch.float64)
    b_from_a[:3, :3], b_from_a[:3, 3] = axis_angle_to_rotation_matrix(p[None, 2:5])[0], p[5:8]
    rms = float(r[inlier].square().mean().sqrt()) if inlier.any() else float("inf")
    return PairEstimate(float(torch.exp(p[0])), float(torch.exp(p[1])), b_from_a, rms, int(inlier.sum()) // 2)


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
                 groups: list | None = None, progress: bool = False) -> RigEstimate:
    """Estimate static cameras ``names`` (the first is the reference) from ``timesteps``, each
    ``{name: (image (H, W, 3) uint8, depth (H, W) metres)}``; ``sizes``: (width, height) per camera.

    The cameras are static, so the matches of all timesteps are pooled into one estimate per
    camera pair; ``groups`` (a label per timestep, e.g. its episode; default: four interleaved
    groups) are estimated apart from it too, and their deviation from it is the spread.
    Raises ValueError when a camera cannot be estimated (too few depth-valid matches)."""
    from tqdm.auto import tqdm

    if len(names) < 2:
        raise ValueError("estimating calibration from the frames needs two external cameras that see the scene")
    groups = list(groups) if groups is not None else [i % 4 for i in range(len(timesteps))]
    finals, spreads, used = [], [], []
    for k in range(1, len(names)):
        steps = tqdm(timesteps, desc=f"matching {names[0]}-{names[k]}", unit="timestep", disable=not progress)
        found = [match_pair(s[names[0]][0], s[names[k]][0], s[names[0]][1], s[names[k]][1]) for s in steps]
        pooled = Matches.cat(found)
        if len(pooled) < MIN_MATCHES:
            raise ValueError(f"cameras {names[0]!r} and {names[k]!r}: {len(pooled)} depth-valid feature matches in "
                             f"{len(timesteps)} sampled timesteps (need {MIN_MATCHES}): the cameras may see too "
                             "little in common, or the frames too little texture")  # fmt: skip
        first = estimate_pair(pooled, sizes[0], sizes[k])
        agreeing = _agreeing(pooled, first, sizes[0], sizes[k])
        if len(agreeing) < MIN_MATCHES:
            raise ValueError(f"cameras {names[0]!r} and {names[k]!r}: only {len(agreeing)} of {len(pooled)} feature "
                             "matches agree on one calibration: the cameras may see too little in common")  # fmt: skip
        final = estimate_pair(agreeing, sizes[0], sizes[k], first)
        parts = []
        for label in dict.fromkeys(groups):
            m = _agreeing(Matches.cat([f for f, g in zip(found, groups) if g == label]), final, sizes[0], sizes[k])
            if len(m) >= MIN_MATCHES:
                parts.append(estimate_pair(m, sizes[0], sizes[k], final))
        finals.append(final)
        spreads.append(spread(parts, final))
        used.append(sum(len(f) > 0 for f in found))
    focals = [float(torch.tensor([f.focal_a for f in finals]).median())] + [f.focal_b for f in finals]
    K = torch.stack([_K(f, s) for f, s in zip(focals, sizes)])
    c2w_ref = torch.stack([torch.eye(4, dtype=torch.float64)] + [torch.linalg.inv(f.b_from_a) for f in finals])
    points = _scene_points(timesteps[: min(len(timesteps), 4)], names, K, c2w_ref)
    world_from_ref, levelled = level_frame(points, c2w_ref)
    return RigEstimate(
        names=names, K=K, c2w=world_from_ref @ c2w_ref,
        focal_spread=[max(s[0] for s in spreads)] + [s[1] for s in spreads],
        rotation_spread_deg=[0.0] + [s[2] for s in spreads], center_spread_m=[0.0] + [s[3] for s in spreads],
        timesteps=[max(used)] + used, matches=[max(f.matches for f in finals)] + [f.matches for f in finals],
        rms_px=[finals[0].rms_px] + [f.rms_px for f in finals], levelled=levelled,
    )  # fmt: skip


def _agreeing(m: Matches, e: PairEstimate, size_a, size_b, max_px: float = 4.0) -> Matches:
    """The matches whose reprojection error under ``e`` is within ``max_px`` both ways."""
    ca, cb = _centre(size_a), _centre(size_b)
    R, t = e.b_from_a[:3, :3], e.b_from_a[:3, 3]
    xb = _lift(m.uv_a, m.z_a, e.focal_a, ca) @ R.T + t
    xa = (_lift(m.uv_b, m.z_b, e.focal_b, cb) - t) @ R
    ub = e.focal_b * xb[:, :2] / xb[:, 2:].clamp_min(1e-6) + cb - m.uv_b
    ua = e.focal_a * xa[:, :2] / xa[:, 2:].clamp_min(1e-6) + ca - m.uv_a
    return m.subset((ub.norm(dim=-1) <= max_px) & (ua.norm(dim=-1) <= max_px))


def _K(f: float, size: tuple[int, int]) -> torch.Tensor:
    return torch.tensor([[f, 0, size[0] / 2], [0, f, size[1] / 2], [0, 0, 1]], dtype=torch.float64)


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
