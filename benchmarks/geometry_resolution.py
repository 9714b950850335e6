"""What the size the model sees costs and gives on the RGB-only geometry path (``max_pixels``).

    python benchmarks/geometry_resolution.py [--quick] [--scenes 4] [--out PATH]

The shipped small model (trained on 112x112 views) runs on two calibrated views of held-out
procedural tabletops (``TabletopScene`` seeds from 900000, never trained on) at the frame
sizes datasets have, 224x224 and 640x480, with its input capped at several ``max_pixels``
(None: no cap, the frame size rounded to multiples of 14; 12,544, the size it was trained at,
is its default). Per setting:

* ``cpu_s``: CPU seconds of one ``predict_depth`` (both views, torch on one thread);
* ``absrel`` / ``delta1``: the predicted depth against the scene's true depth at the model's
  size (true depth taken at the nearest pixel): mean |d - d*| / d*, and the share of pixels
  with max(d / d*, d* / d) < 1.25;
* ``psnr_large`` / ``sharpness_large``: a novel view: the left camera moved at level
  ``large`` (two draws per scene), rendered with hole filling from discs built at the frame
  size from the frames' colours and the model's depth (taken at the nearest pixels), as the
  transform builds them from such a cache, against the scene's true image there (PSNR, and
  detail over the true image's, :func:`~gensplat_transforms.core.metrics.sharpness_ratio`);
  ``psnr_large_small`` / ``sharpness_large_small``: the same view rendered from discs at the
  model's size and resized to the frame size (bilinear), for comparison.

Writes benchmarks/results/geometry_resolution.json (outputs/benchmarks_quick/ with ``--quick``; or
``--out``) and prints a table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as F
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.core.metrics import psnr, sharpness_ratio
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import GeometryReconstructor, Views
from gensplat_transforms.geometry.base import nearest_pixels
from gensplat_transforms.geometry.feedforward import model_size
from gensplat_transforms.transform import GenSplatConfig, render_view
from gensplat_transforms.views.perturbation import PaperSampler

FIRST_SEED = 900_000
SETTINGS = {(224, 224): (None, 25_000, 12_544, 8_000),
            (640, 480): (None, 255_000, 50_000, 25_000, 12_544, 8_000)}  # fmt: skip


def depth_errors(pred: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """(AbsRel, delta < 1.25) of (V, 1, h, w) depth against the truth at that size."""
    ok = (truth > 0) & (pred > 0)
    rel = ((pred - truth).abs() / truth)[ok]
    ratio = torch.maximum(pred / truth, truth / pred)[ok]
    return float(rel.mean()), float((ratio < 1.25).float().mean())


def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(1)
    config, sampler = GenSplatConfig(), PaperSampler("large", seed=0)
    sizes = {(224, 224): (None, 12_544)} if args.quick else SETTINGS
    rows = []
    for (width, height), caps in sizes.items():
        cameras = default_cameras(width, height)[:2]
        scenes = [TabletopScene(FIRST_SEED + i) for i in range(args.scenes)]
        truth = [scene.render(cameras) for scene in scenes]
        for cap in caps:
            rec = GeometryReconstructor(max_pixels=cap or 2 * width * height)  # None: no cap
            h, w = model_size(height, width, cap)
            cpu, errors, scores = [], [], []
            for i, (scene, (images, depth)) in enumerate(zip(scenes, truth)):
                views = Views(images, cameras)
                t0 = time.process_time()
                out = rec.predict_depth(views)
                cpu.append(time.process_time() - t0)
                errors.append(depth_errors(out.depths, nearest_pixels(depth, w, h)))
                discs = Views(images, cameras, nearest_pixels(out.depths, width, height))
                full, small = rec.assemble(discs), rec.assemble(out)
                for draw in range(2):
                    moved = sampler.sample(i, view=draw).move(cameras, 0)[0]
                    view, true_view = render_view(full, moved, config).rgb, scene.render(moved)[0]
                    resized = F.interpolate(render_view(small, moved.resize(w, h), config).rgb, size=(height, width),
                                            mode="bilinear", align_corners=False).clamp(0, 1)  # fmt: skip
                    scores.append((psnr(view, true_view), sharpness_ratio(view, true_view),
                                   psnr(resized, true_view), sharpness_ratio(resized, true_view)))  # fmt: skip
            row = {
                "frame": [width, height], "max_pixels": cap, "model_size": [w, h],
                "cpu_s": round(statistics.median(cpu), 3),
                "absrel": round(statistics.mean(e[0] for e in errors), 4),
                "delta1": round(statistics.mean(e[1] for e in errors), 4),
                "psnr_large": round(statistics.mean(s[0] for s in scores), 2),
                "sharpness_large": round(statistics.mean(s[1] for s in scores), 3),
                "psnr_large_small": round(statistics.mean(s[2] for s in scores), 2),
                "sharpness_large_small": round(statistics.mean(s[3] for s in scores), 3),
            }  # fmt: skip
            rows.append(row)
            print(f"{width}x{height} max_pixels {cap!s:>7} -> model {w}x{h}: {row['cpu_s']:.3f} CPU s, "
                  f"AbsRel {row['absrel']:.3f}, delta1 {row['delta1']:.3f}, PSNR at large {row['psnr_large']:.2f} dB, "
                  f"sharpness {row['sharpness_large']:.2f} (rendered at the model's size: {row['psnr_large_small']:.2f} dB, "
                  f"{row['sharpness_large_small']:.2f})",
                  flush=True)  # fmt: skip
    return {
        "quick": args.quick, "scenes_per_size": args.scenes, "draws_per_scene": 2, "first_seed": FIRST_SEED,
        "model": "gensplat_transforms/weights/small (trained at 112x112)", "torch_threads": 1, "rows": rows,
        "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg(),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="224x224 only, two settings, one scene")
    parser.add_argument("--scenes", type=int, default=None, help="scenes per frame size (default: 4, 1 with --quick)")
    parser.add_argument("--out", type=Path, help=out_help("geometry_resolution.json"))
    args = parser.parse_args()
    args.out = args.out or default_out("geometry_resolution.json", args.quick)
    args.scenes = args.scenes or (1 if args.quick else 4)
    write_result(run(args), args.out)


if __name__ == "__main__":
    main()
