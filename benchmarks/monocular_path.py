"""The RGB-only path with a single-image model (MoGe-2), measured where the truth is known.

    python benchmarks/monocular_path.py [--quick] [--root DATASET] [--out DIR]

MoGe-2's released weights cannot be fetched here, and random weights say nothing about
quality. So the network is replaced by an oracle of its outputs (:class:`OracleMoGe2`: for the
image it is shown, the simulator's true camera-frame points, a mask where there is depth and a
metric scale), and everything after the network runs as shipped: MoGe-2's focal and shift
recovery, :class:`MonocularReconstructor`, ``gensplat calibrate estimate --model`` and the
cache build's per-episode scale alignment. The oracle is perfect (``perfect``) or, as a
single-image metric model wavers, each image's scale is off by a log-normal factor of
``--scale-noise`` (default 0.1: about 10 %; ``noisy``). A held-out recording (MP4, as users'
datasets are) is copied without its calibration and its depth, and on each copy:

* **calibration** (``estimate_calibration`` with the oracle's reconstructor, nothing else
  given): focal, pose and scale errors against the recorded calibration
  (``self_calibration.errors``), the focal spread it reports, its time;
* **novel views** at the paper's levels (the left camera moved; PSNR / SSIM against the
  simulator's image at the pose the move means): ``rgbd_true`` (the recorded depth and
  calibration: what a RGB-D dataset gets), ``monocular`` (the oracle's depth as a cache build
  makes it: every frame of the episode predicted, scales aligned to the first frames; the
  estimated calibration), ``monocular_unaligned`` (each frame's own prediction), ``forward_warp``
  (the recorded depth, nearest pixel) and ``geometry_small`` (the shipped geometry model's depth
  on the recorded calibration).

**Cost** of the real network per frame on one CPU thread (CPU seconds; random weights, the
official token count): the released ViT-L (:data:`VITL_CONFIG`) and a ViT-S backbone with the
same neck and heads (the released ViT-S checkpoint's neck is not known here: an upper bound
for it), at 224x224 and 480x640, one ``infer`` with the post-processing, the best of ``--repeats``.

Writes ``benchmarks/results/monocular_path.json`` (into ``--out`` when given, into
``outputs/benchmarks_quick/`` with ``--quick``).
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import torch
import torch.nn.functional as F
from gensplat_lerobot import LeRobotSource
from gensplat_lerobot.estimate import estimate_calibration
from gensplat_sim.truth import GroundTruth
from machine import cpu_model, default_out, write_result
from nvs_fidelity import draw, frame_size_geometry, score
from self_calibration import NAMES, REPO, errors, heldout_parser, heldout_run, uncalibrated_copy

from gensplat_transforms.calibration.estimate import EstimateConfig
from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.geometry import (
    GeometryReconstructor,
    MonocularReconstructor,
    RGBDReconstructor,
    Views,
)
from gensplat_transforms.geometry.model.moge import VITL_CONFIG, MoGe2, MoGe2Config, model_config, unproject
from gensplat_transforms.rendering.warp import forward_warp
from gensplat_transforms.views.perturbation import EVAL_LEVELS, PaperSampler

#: the oracle's network: never run, it only gives MoGe2 its config and weights hash
ORACLE_CONFIG = model_config("dinov2_vits14", [8, 8, 8, 8, 8], [384, 1], [11])
SIGNATURE = 12  # images are told apart by their mean colours on a SIGNATURE x SIGNATURE grid
METHODS = ("rgbd_true", "monocular", "monocular_unaligned", "forward_warp", "geometry_small")


def central_square(x: torch.Tensor) -> torch.Tensor:
    """The central square of (..., H, W), as ``predict_cameras`` shows an image to the model."""
    H, W = x.shape[-2:]
    s = min(H, W)
    return x[..., (H - s) // 2 : (H - s) // 2 + s, (W - s) // 2 : (W - s) // 2 + s]


def signature(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) -> (3 * SIGNATURE**2,) mean colours on a coarse grid."""
    return F.adaptive_avg_pool2d(image[None].float(), SIGNATURE).flatten()


class FrameIndex:
    """Every image of a recording by :func:`signature`, whole and its central square:
    ``keys`` [(episode, frame, camera)], ``signatures`` {square: (N, 3 * SIGNATURE**2)}."""

    def __init__(self, source: LeRobotSource) -> None:
        self.keys, full, square = [], [], []
        for ep in range(source.dataset.meta.total_episodes):
            for fr in range(source.num_frames(ep)):
                for cam, image in enumerate(source.views(ep, fr).images):
                    self.keys.append((ep, fr, cam))
                    full.append(signature(image))
                    square.append(signature(central_square(image)))
        self.signatures = {False: torch.stack(full), True: torch.stack(square)}


class OracleMoGe2(MoGe2):
    """MoGe-2's interface answering with the truth: :meth:`forward` of an image of the recording
    (whole, or its central square, at any size) gives its true camera-frame points, a mask where
    it has depth and a metric scale of 1, or with ``scale_noise`` a log-normal factor per
    (episode, frame, camera), seeded, the points divided by it (a model's scale error)."""

    def __init__(self, source: LeRobotSource, index: FrameIndex, scale_noise: float = 0.0, seed: int = 0) -> None:
        super().__init__(MoGe2Config.from_dict(ORACLE_CONFIG))
        self.source, self.index, self.scale_noise, self.seed = source, index, scale_noise, seed
        self._views: tuple | None = None
        self.lookups: list[float] = []  # each lookup's signature distance (0: the same decoded frame)

    def _truth(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, float]:
        """The true depth (h, w) and normalised K (3, 3) of (3, h, w) ``image``, and its scale factor."""
        h, w = image.shape[-2:]
        square = h == w and self.source.cameras.height != self.source.cameras.width
        dist = (self.index.signatures[square] - signature(image)).norm(dim=1)
        ep, fr, cam = self.index.keys[int(dist.argmin())]
        self.lookups.append(float(dist.min()))
        if self._views is None or self._views[0] != (ep, fr):
            self._views = ((ep, fr), self.source.views(ep, fr))
        views = self._views[1]
        depth, K = views.depths[cam, 0].double(), views.cameras.K[cam].double().clone()
        if square:
            depth = central_square(depth)
            K[:2, 2] = min(views.cameras.width, views.cameras.height) / 2
        side_w, side_h = depth.shape[-1], depth.shape[-2]
        depth = F.interpolate(depth[None, None], size=(h, w), mode="nearest")[0, 0]
        K = torch.diag(torch.tensor([w / side_w, h / side_h, 1.0], dtype=torch.float64)) @ K
        Kn = K / torch.tensor([w, h, 1.0], dtype=torch.float64)[:, None]
        rng = np.random.default_rng([self.seed, ep, fr, cam])
        factor = float(np.exp(self.scale_noise * rng.standard_normal())) if self.scale_noise else 1.0
        return depth, Kn, factor

    def forward(self, images: torch.Tensor, num_tokens: int) -> dict[str, torch.Tensor]:
        truths = [self._truth(image) for image in images]
        depth = torch.stack([d for d, _, _ in truths])
        points = unproject(depth, torch.stack([k for _, k, _ in truths]))
        scale = torch.tensor([f for _, _, f in truths], dtype=torch.float64)
        return {"points": points.float(), "mask": (depth > 0).float(), "metric_scale": scale.float()}


def baseline(cameras: Cameras) -> float:
    """The distance between the first two cameras' centres (m)."""
    return float((cameras.c2w[1, :3, 3] - cameras.c2w[0, :3, 3]).norm())


def episode_depths(rec: MonocularReconstructor, source: LeRobotSource, ep: int, aligned: bool) -> list[torch.Tensor]:
    """(V, 1, H, W) depth of every frame of episode ``ep`` on the source's cameras, as a cache
    build predicts it (``aligned``: :meth:`~MonocularReconstructor.predict_depths`)."""
    frames = (Views(source.views(ep, fr).images, source.cameras) for fr in range(source.num_frames(ep)))
    if aligned:
        return [v.depths for v in rec.predict_depths(frames)]
    return [rec.predict_depth(v).depths for v in frames]


def novel_views(calibrated: LeRobotSource, estimated: LeRobotSource, oracle: OracleMoGe2, truth: GroundTruth,
                frames: list[tuple[int, int]], draws: int) -> dict:  # fmt: skip
    """{level: {method: mean PSNR / SSIM / visible PSNR}} of the left camera's moved views."""
    rec = MonocularReconstructor(oracle)
    geometry = GeometryReconstructor()
    rows = {level: {m: [] for m in METHODS} for level in EVAL_LEVELS}
    depth = {}
    for ep in sorted({ep for ep, _ in frames}):
        for aligned in (True, False):
            depth[ep, aligned] = episode_depths(rec, estimated, ep, aligned)
    to_world = calibrated.cameras.c2w[0] @ torch.linalg.inv(estimated.cameras.c2w[0])
    for ep, fr in frames:
        views = calibrated.views(ep, fr)
        recs = {"rgbd_true": RGBDReconstructor().reconstruct(views),
                "monocular": rec.assemble(Views(views.images, estimated.cameras, depth[ep, True][fr])),
                "monocular_unaligned": rec.assemble(Views(views.images, estimated.cameras, depth[ep, False][fr])),
                "geometry_small": frame_size_geometry(geometry, views.images, calibrated.cameras)}  # fmt: skip
        for level in EVAL_LEVELS:
            sampler = PaperSampler(level, seed=0)
            for d in range(1 if level == "none" else draws):
                p = sampler.sample(ep, view=d)
                target = p.move(calibrated.cameras, 0)
                gt = truth.render(ep, fr, target)[0][0]
                warped, filled = forward_warp(views.images, views.depths, calibrated.cameras, target)
                seen = draw(recs["rgbd_true"], target).alpha[0] > 0.5
                outs = {m: draw(r, target).rgb[0] for m, r in recs.items() if m not in ("monocular", "monocular_unaligned")}
                outs["forward_warp"] = warped[0]
                moved = p.move(estimated.cameras, 0)  # the estimate's move, its truth mapped into the world
                real = Cameras(calibrated.cameras.K[:1], to_world @ moved.c2w, moved.width, moved.height)
                gt_est = truth.render(ep, fr, real)[0][0]
                for m in ("monocular", "monocular_unaligned"):
                    rows[level][m].append(score(draw(recs[m], moved).rgb[0], gt_est, seen, filled[0]))
                for m, out in outs.items():
                    rows[level][m].append(score(out, gt, seen, filled[0]))
    keys = ("psnr", "ssim", "psnr_visible")
    return {level: {m: {k: float(np.mean([r[k] for r in v])) for k in keys} for m, v in by.items()}
            for level, by in rows.items()}  # fmt: skip


def network_cost(repeats: int) -> dict:
    """{architecture: {size: CPU seconds}} of MoGe-2's ``infer`` on one image, one CPU thread,
    random weights (CPU time: other work on the machine barely moves it)."""
    vits = model_config("dinov2_vits14", [1024, 256, 128, 64, 32], [384, 1024, 1024, 1], [2, 5, 8, 11])
    out = {}
    for name, config in (("vits_backbone_vitl_neck", vits), ("vitl", VITL_CONFIG)):
        model = MoGe2(MoGe2Config.from_dict(config)).eval()
        out[name] = {"parameters_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 1)}
        for h, w in ((224, 224), (480, 640)):
            image = torch.rand(1, 3, h, w, generator=torch.Generator().manual_seed(0))
            times = []
            for _ in range(repeats):
                t0 = time.process_time()
                with torch.no_grad():
                    model.infer(image)
                times.append(time.process_time() - t0)
            out[name][f"{h}x{w}_cpu_s"] = round(min(times), 3)
        del model
    return out


def main() -> None:
    parser = heldout_parser(__doc__.splitlines()[0], "240x320, 1 episode, 4 timesteps, 1 draw, no network cost")
    parser.add_argument("--scale-noise", type=float, default=0.1, help="the noisy oracle's log-scale sigma")
    parser.add_argument("--repeats", type=int, default=2, help="network cost: forwards per size (best kept)")
    args = parser.parse_args()
    args.out = args.out or default_out("", args.quick)
    work = Path(tempfile.mkdtemp(prefix="monocular_path_"))
    root, calibrated, truth, frames = heldout_run(args, work)
    total = calibrated.dataset.meta.total_episodes
    timesteps, draws = (4, 1) if args.quick else (args.timesteps, args.draws)
    result: dict = {}
    torch.set_num_threads(1)
    index = FrameIndex(calibrated)
    for variant, noise in (("perfect", 0.0), ("noisy", args.scale_noise)):
        oracle = OracleMoGe2(calibrated, index, noise)
        copy = uncalibrated_copy(root, work / variant, "none")
        t0 = time.perf_counter()
        config = EstimateConfig(timesteps=timesteps, model=MonocularReconstructor(oracle))
        rig = estimate_calibration(copy, REPO, NAMES, config, progress=False)
        seconds = time.perf_counter() - t0
        estimated = LeRobotSource(copy, REPO, NAMES)
        result[variant] = {
            "scale_noise": noise, **errors(calibrated.cameras, estimated.cameras),
            "scale_error": abs(baseline(estimated.cameras) / baseline(calibrated.cameras) - 1), "seconds": round(seconds, 1),
            "scale": rig.scale, "focal_spread": rig.focal_spread, "matches": rig.matches[1],
            "novel_views": novel_views(calibrated, estimated, oracle, truth, frames, draws),
            "max_lookup_distance": max(oracle.lookups),
        }  # fmt: skip
    result["network_cost"] = {} if args.quick else network_cost(args.repeats)
    result["settings"] = {"quick": args.quick, "image_size": [calibrated.cameras.height, calibrated.cameras.width],
                          "episodes": total, "frames": len(frames), "draws_per_level": draws, "timesteps": timesteps,
                          "dataset": "recorded held-out" if args.root is None else root.name, "video": "MP4",
                          **cpu_model(), "torch_threads": 1}  # fmt: skip
    write_result(result, args.out / "monocular_path.json")
    for variant in ("perfect", "noisy"):
        r = result[variant]
        print(f"{variant} (scale noise {r['scale_noise']:g}): focal {max(r['focal_error']):.2%}, rotation "
              f"{r['rotation_error_deg']:.2f} deg, centre {r['center_error_m'] * 100:.2f} cm of "
              f"{r['baseline_m']:.2f} m, scale {r['scale_error']:.2%}, up {r['up_error_deg']:.2f} deg; {r['seconds']} s")  # fmt: skip
        print(f"{'level':>8} " + " ".join(f"{m:>20}" for m in METHODS))
        for level, v in r["novel_views"].items():
            print(f"{level:>8} " + " ".join(f"{v[m]['psnr']:20.2f}" for m in METHODS))
    for name, cost in result["network_cost"].items():
        print(f"{name}: {cost}")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
