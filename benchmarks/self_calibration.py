"""Calibration estimated from a recording's own frames, against the recorded calibration.

    python benchmarks/self_calibration.py [--quick] [--root DATASET] [--out DIR]

A held-out simulated pick-and-place recording (480x640 MP4 with depth sidecars; ``--root``:
one recorded with ``gensplat record``) is copied with its calibration removed: with its
exact depth (``depth``), with the depth a RealSense D435-like sensor measures there
(``sensor_depth``: noise, holes, 1 mm steps; ``gensplat_sim.sensor``, seeded per frame), and RGB only
with the cameras' true field of view and distance given (``rgb_given_fov``) or the field of
view 5 % too wide (``rgb_fov_5pct_wide``), and RGB only with nothing given: the shipped
model's focal lengths and metric depth (``rgb_model``, ``gensplat calibrate estimate
--model``), or its focal lengths and the true distance (``rgb_model_baseline``). On each copy
``gensplat calibrate estimate``
(``estimate_calibration``) runs, and is scored against the
recorded calibration: focal lengths (relative error), the right camera's rotation and centre
seen from the left camera, the world's up direction and the pivot (both seen from the left
camera), the spread it reports, and its time.

Novel views: at sampled frames the left camera is moved by the ``nvs_fidelity`` levels' draws,
and the RGB-D render (``RGBDReconstructor``, fast renderer, holes not filled) is compared with
the simulator's image at the pose the move means for the real camera, once for the recorded
calibration (``calibrated``) and once for the estimate (``estimated``; its moves are made in
its own levelled frame, and the truth is rendered there, mapped into the simulator's world
through the left camera). Both use the same depth (the recording's for the RGB-only copies:
what is measured is the calibration's effect) and the same draws. The model copies add
``estimated_geometry``: the estimate with the depth of the shipped model (``gensplat cache``'s
geometry path: predicted at the model's size, read at the image's nearest pixels), what a user
without depth trains on.

Writes ``benchmarks/results/self_calibration.json`` (into ``--out`` when given, and into
``outputs/benchmarks_quick/`` with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import numpy as np
import torch
from gensplat_lerobot import LeRobotSource
from gensplat_lerobot.estimate import estimate_calibration
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.sensor import SensorDepthConfig, sensor_depth
from gensplat_sim.truth import GroundTruth
from gensplat_sim.world import WorldConfig
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.calibration.estimate import EstimateConfig, rotation_angle_deg
from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.metrics import psnr, ssim
from gensplat_transforms.core.views import nearest_pixels
from gensplat_transforms.data.format import load_depth, save_depth
from gensplat_transforms.geometry import GeometryReconstructor, RGBDReconstructor, Views
from gensplat_transforms.rendering import render
from gensplat_transforms.views.perturbation import EVAL_LEVELS, PaperSampler, pivot_point
from gensplat_transforms.weights import DEFAULT_MODEL_DIR

REPO = "gensplat/sim_pick_place_heldout"
HELDOUT_SEED = 1000
NAMES = ("left", "right")


def uncalibrated_copy(root: Path, out: Path, depth: str) -> Path:
    """``root`` copied to ``out`` without the cameras' calibration (their features' ``camera.*``
    info); ``depth``: "exact" keeps its depth sidecars, "sensor" makes them the simulated
    sensor's (seeded per frame), "none" leaves them out."""
    shutil.copytree(root, out, ignore=shutil.ignore_patterns("gensplat", *(("depth",) if depth == "none" else ())))
    path = out / "meta" / "info.json"
    info = json.loads(path.read_text())
    for ft in info["features"].values():
        if ft.get("info"):
            ft["info"] = {k: v for k, v in ft["info"].items() if not k.startswith("camera.")}
    path.write_text(json.dumps(info, indent=4))
    if depth == "sensor":
        source = LeRobotSource(root, REPO, NAMES)
        for ep in range(source.dataset.meta.total_episodes):
            for i, n in enumerate(NAMES):
                depth = load_depth(root, n, ep)
                frames = [sensor_depth(depth[t, 0], source.views(ep, t).images[i], source.cameras.K[i],
                                       SensorDepthConfig(), torch.Generator().manual_seed(1000 * ep + t))
                          for t in range(len(depth))]  # fmt: skip
                save_depth(out, n, ep, torch.stack(frames))
    return out


def errors(true: Cameras, est: Cameras) -> dict:
    """The estimate's errors against the truth, everything seen from the left camera."""
    rel = lambda c: torch.linalg.inv(c.c2w[0]) @ c.c2w[1]
    up = lambda c: c.c2w[0, 2, :3]
    pivot = lambda c: (torch.linalg.inv(c.c2w[0]) @ torch.cat([pivot_point(c.c2w[0], c.c2w[1]),
                                                                torch.ones(1, dtype=torch.float64)]))[:3]  # fmt: skip
    baseline = float(rel(true)[:3, 3].norm())
    return {
        "focal_error": [abs(float(e / t) - 1) for e, t in zip(est.K[:, 0, 0], true.K[:, 0, 0])],
        "rotation_error_deg": float(rotation_angle_deg(rel(est)[:3, :3] @ rel(true)[:3, :3].T)),
        "center_error_m": float((rel(est)[:3, 3] - rel(true)[:3, 3]).norm()), "baseline_m": baseline,
        "up_error_deg": math.degrees(math.acos(min(1.0, float(up(est) @ up(true))))),
        "pivot_error_m": float((pivot(est) - pivot(true)).norm()),
    }  # fmt: skip


def novel_views(calibrated: LeRobotSource, estimated: LeRobotSource, truth: GroundTruth, frames, draws: int,
                geometry: bool = False) -> dict:  # fmt: skip
    """{level: {calibrated, estimated[, estimated_geometry]: mean PSNR / SSIM}} of the left
    camera's moved views (``geometry``: also the estimate with the shipped model's depth)."""
    names = ("calibrated", "estimated", *(("estimated_geometry",) if geometry else ()))
    rows = {level: {name: [] for name in names} for level in EVAL_LEVELS}
    model = GeometryReconstructor() if geometry else None
    for ep, fr in frames:
        est_views = estimated.views(ep, fr)  # the copy's depth: exact or the sensor's; none: the recording's
        if est_views.depths is None:
            est_views = Views(est_views.images, est_views.cameras, calibrated.views(ep, fr).depths)
        cal_views = Views(est_views.images, calibrated.cameras, est_views.depths)
        recs = {"calibrated": RGBDReconstructor().reconstruct(cal_views),
                "estimated": RGBDReconstructor().reconstruct(est_views)}
        if geometry:  # as the transform reads a geometry cache: the model's depth at the image's pixels
            depth = model.predict_depth(Views(est_views.images, estimated.cameras)).depths
            H, W = est_views.images.shape[-2:]
            recs["estimated_geometry"] = model.assemble(Views(est_views.images, estimated.cameras,
                                                              nearest_pixels(depth, W, H)))  # fmt: skip
        to_world = calibrated.cameras.c2w[0] @ torch.linalg.inv(estimated.cameras.c2w[0])
        for level in EVAL_LEVELS:
            sampler = PaperSampler(level, seed=0)
            for d in range(1 if level == "none" else draws):
                p = sampler.sample(ep, view=d)
                for name in names:
                    source = calibrated if name == "calibrated" else estimated
                    target = p.move(source.cameras, 0)
                    real = Cameras(calibrated.cameras.K[:1], (to_world if name != "calibrated" else torch.eye(4,
                                   dtype=torch.float64)) @ target.c2w, target.width, target.height)  # fmt: skip
                    gt = truth.render(ep, fr, real)[0][0]
                    out = render(recs[name].gaussians, target, backend="fast", return_depth=False).rgb[0].clamp(0, 1)
                    rows[level][name].append((psnr(out, gt), ssim(out, gt)))
    return {level: {name: {"psnr": float(np.mean([r[0] for r in v])), "ssim": float(np.mean([r[1] for r in v]))}
                    for name, v in by.items()} for level, by in rows.items()}  # fmt: skip


def heldout_run(args, work: Path) -> tuple[Path, LeRobotSource, GroundTruth, list[tuple[int, int]]]:
    """The recording a run scores on: ``args.root``, or held-out episodes recorded into ``work``
    (480x640 MP4, 3 episodes; 240x320, 1 with ``args.quick``); its calibrated source, its truth
    and the frames the novel views are scored at (two inner frames per episode)."""
    root = args.root
    if root is None:
        height, width, episodes = (240, 320, 1) if args.quick else (480, 640, 3)
        root = work / "recorded"
        record(RecordConfig(root, "pick_place", episodes, HELDOUT_SEED, repo_id=REPO,
                            world=WorldConfig(height=height, width=width)), progress=False)  # fmt: skip
    calibrated = LeRobotSource(root, REPO, NAMES)
    total = calibrated.dataset.meta.total_episodes
    frames = [(ep, round(k * (calibrated.num_frames(ep) - 1) / 3)) for ep in range(total) for k in (1, 2)]
    return root, calibrated, GroundTruth(root), frames


def heldout_parser(description: str, quick: str) -> argparse.ArgumentParser:
    """The options of a run on :func:`heldout_run`'s recording: ``--quick`` (``quick`` says what
    it runs), ``--root``, ``--timesteps`` the estimate samples, ``--draws`` and ``--out``."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--quick", action="store_true", help=quick)
    parser.add_argument("--root", type=Path, help="a recorded simulated dataset (default: record held-out episodes)")
    parser.add_argument("--timesteps", type=int, default=16, help="timesteps the estimate samples (default: 16)")
    parser.add_argument("--draws", type=int, default=3, help="moves per level and frame (default: 3)")
    parser.add_argument("--out", type=Path, help=out_help(""))
    return parser


def main() -> None:
    parser = heldout_parser(__doc__.splitlines()[0], "240x320, 1 episode, 4 timesteps, 1 draw, 4 variants")
    args = parser.parse_args()
    args.out = args.out or default_out("", args.quick)
    torch.set_num_threads(1)
    work = Path(tempfile.mkdtemp(prefix="self_calibration_"))
    root, calibrated, truth, frames = heldout_run(args, work)
    total = calibrated.dataset.meta.total_episodes
    timesteps, draws = (4, 1) if args.quick else (args.timesteps, args.draws)
    result = {}
    K, c2w = calibrated.cameras.K, calibrated.cameras.c2w
    fov = math.degrees(2 * math.atan(calibrated.cameras.width / 2 / float(K[0, 0, 0])))
    baseline = float((c2w[1, :3, 3] - c2w[0, :3, 3]).norm())
    variants = {"depth": ("exact", {}), "sensor_depth": ("sensor", {}),  # focal lengths and scale estimated
                "rgb_given_fov": ("none", {"fov_deg": fov, "baseline_m": baseline}),  # both given exactly
                "rgb_fov_5pct_wide": ("none", {"fov_deg": fov * 1.05, "baseline_m": baseline}),
                "rgb_model": ("none", {"model": str(DEFAULT_MODEL_DIR)}),  # focal lengths and scale from the model
                "rgb_model_baseline": ("none", {"model": str(DEFAULT_MODEL_DIR), "baseline_m": baseline})}  # fmt: skip
    if args.quick:  # one variant per kind of input: depth, the sensor's depth, RGB with what is given, the model
        variants = {k: variants[k] for k in ("depth", "sensor_depth", "rgb_given_fov", "rgb_model")}
    for variant, (depth, given) in variants.items():
        copy = uncalibrated_copy(root, work / variant, depth)
        t0, cpu0 = time.perf_counter(), time.process_time()
        rig = estimate_calibration(copy, REPO, NAMES, EstimateConfig(timesteps=timesteps, **given), progress=False)
        seconds, cpu = time.perf_counter() - t0, time.process_time() - cpu0
        estimated = LeRobotSource(copy, REPO, NAMES)
        result[variant] = {
            **errors(calibrated.cameras, estimated.cameras), "seconds": round(seconds, 1), "cpu_seconds": round(cpu, 1),
            "given": {k: ("shipped" if k == "model" else v) for k, v in given.items()}, "timesteps": timesteps, "matches": rig.matches[1], "rms_px": rig.rms_px[1],
            "levelled": rig.levelled, "scale": rig.scale,
            "spread": {"focal": [None if math.isnan(f) else f for f in rig.focal_spread],
                       "rotation_deg": rig.rotation_spread_deg[1],
                       "center_m": rig.center_spread_m[1]},
            "novel_views": novel_views(calibrated, estimated, truth, frames, draws, geometry="model" in given),
        }  # fmt: skip
    result["settings"] = {"quick": args.quick, "image_size": [calibrated.cameras.height, calibrated.cameras.width],
                          "episodes": total, "frames": len(frames), "draws_per_level": draws,
                          "dataset": "recorded held-out" if args.root is None else root.name,
                          "video": "MP4" if args.root is None else "as given", **cpu_model(), "torch_threads": 1}  # fmt: skip
    write_result(result, args.out / "self_calibration.json")
    for variant in variants:
        r = result[variant]
        print(f"{variant}: focal {max(r['focal_error']):.2%}, rotation {r['rotation_error_deg']:.2f} deg, centre "
              f"{r['center_error_m'] * 100:.2f} cm of {r['baseline_m']:.2f} m, up {r['up_error_deg']:.2f} deg, pivot "
              f"{r['pivot_error_m'] * 100:.2f} cm; {r['matches']} matches, {r['seconds']} s")  # fmt: skip
        print(f"{'level':>8} {'calibrated dB':>14} {'estimated dB':>13} {'delta':>7} {'model depth dB':>15}")
        for level, v in r["novel_views"].items():
            c, e = v["calibrated"]["psnr"], v["estimated"]["psnr"]
            g = f"{v['estimated_geometry']['psnr']:15.2f}" if "estimated_geometry" in v else ""
            print(f"{level:>8} {c:14.2f} {e:13.2f} {e - c:+7.2f} {g}")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
