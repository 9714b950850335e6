"""Quality and speed of the feed-forward GenSplat model against exact ground truth.

    python benchmarks/model_quality.py [--quick] [--model DIR] [--ablation NAME=DIR ...] [--out FILE]

Held-out procedural tabletops (``TabletopScene`` seeds from 100000 on; training used seeds
below 10000) are seen by the two default external cameras (left, right) at 112x112, the
model's training size. Per scene:

* geometry, from the model's raw outputs on the two RGB images: relative rotation error
  (deg) and relative translation error (m, and its direction in deg) between the predicted
  and true camera pair, point-map error (mean distance, m, camera frame) and depth AbsRel
  of the local point maps against the ray-cast depth, as predicted (metric) and after
  aligning each scene's scale by the median depth ratio;
* novel views: one source camera (left or right, alternating) is moved by
  ``PaperSampler(level).sample(scene, view=k)`` about the pivot of the true cameras,
  and the Gaussians are rendered there and compared with ``TabletopScene.render`` (exact
  ray casting): PSNR over the image, and depth MAE (m) over the pixels the render covers
  (alpha > 0.5) and the truth sees. ``gensplat`` is ``GenSplatReconstructor`` on the RGB
  images with the calibrated cameras (default ``placement="per_view"``: each view's
  Gaussians moved with its predicted camera onto its calibrated pose);
  ``gensplat_similarity`` aligns the whole prediction to the calibrated frame by the pose
  similarity instead (``placement="similarity"``); ``rgbd`` is ``RGBDReconstructor`` on the
  true RGB-D views. Level ``none`` re-renders the source cameras;
* inference time per timestep (two views), median over repeats, this CPU, torch's thread
  count as printed.

``--ablation`` evaluates further checkpoints the same way (the paper's ablation: training
with vs without 3D-prior distillation), with their run's training settings when the directory
is a ``gensplat train-model`` export; without it, the previous results' ``ablation`` section
is kept. The model directory's ``training.json`` (how it was trained), when present,
is copied into the results. Writes ``benchmarks/results/model_quality.json`` (``--quick``:
``outputs/benchmarks_quick/model_quality.json``; or ``--out``).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from pathlib import Path

import torch
from machine import default_out, out_help, write_result

from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import GenSplatReconstructor, RGBDReconstructor, Views
from gensplat_transforms.geometry.model import GenSplatModel
from gensplat_transforms.geometry.model.losses import geodesic_angle, relative_poses
from gensplat_transforms.geometry.model.teacher import camera_points
from gensplat_transforms.rendering import render
from gensplat_transforms.views.perturbation import PaperSampler, pivot_point
from gensplat_transforms.weights import DEFAULT_MODEL_DIR

SIZE = 112
FIRST_SEED = 100_000
LEVELS = ("none", "small", "medium", "large")


def geometry_errors(model: GenSplatModel, views: Views) -> dict[str, float]:
    """Pose and point-map errors of the model's raw prediction for one two-view timestep."""
    with torch.no_grad():
        out = model(views.images[None])
    pred = relative_poses(out["camera_poses"].double())[0, 0, 1]  # T_{0<-1}
    true = relative_poses(views.cameras.c2w[None].double())[0, 0, 1]
    t_pred, t_true = pred[:3, 3], true[:3, 3]
    cos = (t_pred @ t_true / (t_pred.norm() * t_true.norm()).clamp_min(1e-12)).clamp(-1, 1)
    points = camera_points(views.depths, views.cameras.K)
    valid = points[..., 2] > 0
    local = out["local_points"][0]
    z_pred, z_true = local[..., 2][valid], points[..., 2][valid]
    z_aligned = z_pred * (z_true / z_pred).median()
    return {
        "rotation_deg": math.degrees(float(geodesic_angle(pred[:3, :3].T @ true[:3, :3]))),
        "translation_m": float((t_pred - t_true).norm()),
        "translation_dir_deg": math.degrees(float(torch.acos(cos))),
        "points_m": float((local - points).norm(dim=-1)[valid].mean()),
        "depth_absrel": float(((z_pred - z_true).abs() / z_true).mean()),
        "depth_absrel_aligned": float(((z_aligned - z_true).abs() / z_true).mean()),
    }


def novel_view_errors(gaussians, target, truth_rgb, truth_depth) -> dict[str, float]:
    """PSNR (dB) and depth MAE (m) of the Gaussians rendered at ``target`` against the truth."""
    r = render(gaussians, target, background=(1.0, 1.0, 1.0))
    mask = (r.alpha > 0.5) & (truth_depth > 0)
    mae = float((r.depth - truth_depth).abs()[mask].mean()) if mask.any() else float("nan")
    return {"psnr": psnr(r.rgb.clamp(0, 1), truth_rgb), "depth_mae_m": mae}


def median_ms(fn, repeats: int) -> float:
    fn()  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t) * 1e3)
    return round(statistics.median(times), 1)


def mean(rows: list[dict]) -> dict[str, float]:
    return {k: round(statistics.fmean(r[k] for r in rows if not math.isnan(r[k])), 4) for k in rows[0]}


def evaluate(model: GenSplatModel, scenes: int, draws: int, with_rgbd: bool) -> dict:
    """Geometry and novel-view errors of ``model`` (and of the RGB-D path) over held-out scenes."""
    cams = default_cameras(SIZE, SIZE)[:2]
    pivot = pivot_point(cams.c2w[0], cams.c2w[1])
    recons = {"gensplat": GenSplatReconstructor(model),
              "gensplat_similarity": GenSplatReconstructor(model, placement="similarity")}  # fmt: skip
    paths = list(recons) + (["rgbd"] if with_rgbd else [])
    geometry, novel = [], {p: {lv: [] for lv in LEVELS} for p in paths}
    for s in range(scenes):
        scene = TabletopScene(FIRST_SEED + s)
        rgb, depth = scene.render(cams)
        views = Views(rgb, cams, depth)
        geometry.append(geometry_errors(model, views))
        gaussians = {name: recon(Views(rgb, cams)).gaussians for name, recon in recons.items()}
        if with_rgbd:
            gaussians["rgbd"] = RGBDReconstructor()(views).gaussians
        for level in LEVELS:
            sampler = PaperSampler(level, seed=0)
            for k in range(1 if level == "none" else draws):
                i = (s + k) % 2
                target = cams[i].with_c2w(
                    sampler.sample(episode_index=s, view=k).apply(cams.c2w[i : i + 1], pivot)
                )
                truth_rgb, truth_depth = scene.render(target)
                for p in paths:
                    novel[p][level].append(novel_view_errors(gaussians[p], target.to(dtype=torch.float32),
                                                             truth_rgb, truth_depth))  # fmt: skip
    return {
        "geometry": mean(geometry),
        "novel_views": {p: {lv: mean(r) for lv, r in v.items()} for p, v in novel.items()},
    }


def timings(model: GenSplatModel, repeats: int) -> dict[str, float]:
    cams = default_cameras(SIZE, SIZE)[:2]
    rgb, depth = TabletopScene(FIRST_SEED).render(cams)
    recon, rgbd = GenSplatReconstructor(model), RGBDReconstructor()
    return {
        "gensplat_ms_per_timestep": median_ms(lambda: recon(Views(rgb, cams)), repeats),
        "rgbd_ms_per_timestep": median_ms(lambda: rgbd(Views(rgb, cams, depth)), repeats),
        "threads": torch.get_num_threads(),
    }


def print_table(result: dict) -> None:
    g = result["model"]["geometry"]
    print(f"geometry (model, {result['settings']['scenes']} scenes): rotation {g['rotation_deg']:.2f} deg, "
          f"translation {100 * g['translation_m']:.1f} cm ({g['translation_dir_deg']:.1f} deg), "
          f"points {100 * g['points_m']:.1f} cm, depth AbsRel {g['depth_absrel']:.3f} "
          f"({g['depth_absrel_aligned']:.3f} scale-aligned)")  # fmt: skip
    print(f"{'path':20}{'level':8}{'PSNR dB':>9}{'depth MAE cm':>14}")
    for path, levels in result["model"]["novel_views"].items():
        for level, m in levels.items():
            print(f"{path:20}{level:8}{m['psnr']:9.2f}{100 * m['depth_mae_m']:14.2f}")
    t = result["timing"]
    print(f"inference per timestep (2 x {SIZE}x{SIZE}, {t['threads']} threads): gensplat "
          f"{t['gensplat_ms_per_timestep']} ms, rgbd {t['rgbd_ms_per_timestep']} ms")  # fmt: skip
    for name, a in result.get("ablation", {}).get("runs", {}).items():
        g = a["geometry"]
        print(f"ablation {name}: rotation {g['rotation_deg']:.2f} deg, depth AbsRel {g['depth_absrel']:.3f} "
              f"({g['depth_absrel_aligned']:.3f} scale-aligned)")  # fmt: skip
        for path, levels in a["novel_views"].items():
            print(f"  {path:20}" + "  ".join(f"{lv} {m['psnr']:.2f} dB / {100 * m['depth_mae_m']:.1f} cm"
                                            for lv, m in levels.items()))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 scene, 1 draw per level, 1 timed run (seconds)")
    parser.add_argument("--model", default=str(DEFAULT_MODEL_DIR), help="model directory (default: shipped)")
    parser.add_argument(
        "--ablation", nargs="+", default=[], metavar="NAME=DIR", help="further models to evaluate"
    )
    parser.add_argument("--out", type=Path, help=out_help("model_quality.json"))
    args = parser.parse_args()
    out = args.out or default_out("model_quality.json", args.quick)
    scenes, draws, repeats = (1, 1, 1) if args.quick else (12, 3, 10)

    model = GenSplatModel.from_pretrained(args.model)
    result = {
        "settings": {"quick": args.quick, "size": SIZE, "scenes": scenes, "draws_per_level": draws,
                     "first_seed": FIRST_SEED,
                     "model": "shipped" if Path(args.model) == DEFAULT_MODEL_DIR else str(args.model)},
        "model": evaluate(model, scenes, draws, with_rgbd=True),
        "timing": timings(model, repeats),
    }  # fmt: skip
    provenance = Path(args.model) / "training.json"
    if provenance.is_file():
        result["training"] = json.loads(provenance.read_text())
    if args.ablation:
        runs = {}
        for spec in args.ablation:
            name, _, directory = spec.partition("=")
            runs[name] = evaluate(GenSplatModel.from_pretrained(directory), scenes, draws, with_rgbd=False)
            run_config = Path(directory).parent / "train_config.json"  # a `gensplat train-model` run
            if run_config.is_file():
                runs[name]["train_config"] = json.loads(run_config.read_text())["train"]
        result["ablation"] = {"settings": dict(result["settings"]), "runs": runs}
    elif out.is_file() and "ablation" in (previous := json.loads(out.read_text())):
        result["ablation"] = previous["ablation"]
    print_table(result)
    write_result(result, out)


if __name__ == "__main__":
    main()
