"""What registering a depth sensor's own maps to the colour camera costs and gives.

    python benchmarks/depth_registration.py [--quick] [--scenes 4] [--out PATH]

LeRobot 0.6 records a RealSense's depth as the depth imager sees it, not registered to the
colour image. Here two calibrated 640x480 colour cameras (focal length 615 px, a D435's
colour imager at that size) each carry a depth sensor like a D435's (focal length 385 px:
a wider view, 15 mm to the side) over held-out procedural tabletops (``TabletopScene`` seeds
from 900000). Per scene and camera, the sensor's own map is:

* used as if registered ("raw": what such a dataset gives without a ``depth`` block in its
  calibration), registered with :func:`~gensplat_transforms.data.registration.register_depth`
  ("registered"), or replaced by the colour camera's true depth ("true");
* compared with the colour camera's true depth: median and 95th-percentile absolute error
  where both have depth, and the share of the colour image that gets depth;
* turned into RGB-D Gaussians of both cameras, rendered (hole-filled, as the transform
  does) with the left camera moved at levels ``medium`` and ``large`` (2 draws each) and
  compared with the scene's true image there (PSNR);
* ``register_ms``: CPU time of one 640x480 registration (one thread, median over the views;
  the first call of a process also loads the compiled code);
* ``render_ms``: CPU time of what a worker renders per replaced camera (registered depth, one
  thread, median): the hole-filled colour view, and the depth sensor's own map at the new
  pose (a second render, from the sensor beside the moved camera).

Writes benchmarks/results/depth_registration.json (outputs/benchmarks_quick/ with ``--quick``; or
``--out``) and prints a table.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import torch
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.data.registration import register_depth
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.transform import GenSplatConfig, render_depth, render_view
from gensplat_transforms.views.perturbation import PaperSampler

FIRST_SEED = 900_000
WIDTH, HEIGHT = 640, 480
COLOUR_FOCAL, DEPTH_FOCAL, BASELINE = 615.0, 385.0, 0.015
LEVELS = ("medium", "large")


def rig() -> tuple[Cameras, Cameras]:
    """The two colour cameras and their depth sensors (each 15 mm along its camera's -x)."""
    colour = default_cameras(WIDTH, HEIGHT)[:2]
    K = torch.tensor([[COLOUR_FOCAL, 0, WIDTH / 2], [0, COLOUR_FOCAL, HEIGHT / 2], [0, 0, 1]], dtype=torch.float64)
    colour = Cameras(K.expand(2, 3, 3).clone(), colour.c2w, WIDTH, HEIGHT)
    Kd = K.clone()
    Kd[0, 0] = Kd[1, 1] = DEPTH_FOCAL
    sensor_in_camera = torch.eye(4, dtype=torch.float64)
    sensor_in_camera[0, 3] = -BASELINE
    return colour, Cameras(Kd.expand(2, 3, 3).clone(), colour.c2w @ sensor_in_camera, WIDTH, HEIGHT)


def run(args: argparse.Namespace) -> dict:
    torch.set_num_threads(1)
    colour, sensors = rig()
    config, rec = GenSplatConfig(), RGBDReconstructor()
    ways = ("raw", "registered", "true")
    errors = {w: [] for w in ways}
    scores = {(w, level): [] for w in ways for level in LEVELS}
    times, render_ms = [], {"colour": [], "sensor_depth": []}
    for i in range(args.scenes):
        scene = TabletopScene(FIRST_SEED + i)
        images, truth = scene.render(colour)
        raw = scene.render(sensors)[1]
        registered = []
        for v in range(2):
            t0 = time.thread_time()
            registered.append(register_depth(raw[v], sensors[v : v + 1], colour[v : v + 1]))
            times.append(time.thread_time() - t0)
        depths = {"raw": raw, "registered": torch.stack(registered), "true": truth}
        for way, depth in depths.items():
            both = (depth > 0) & (truth > 0)
            e = (depth - truth)[both].abs()
            errors[way].append((float(e.median()), float(e.quantile(0.95)), float(both.float().mean())))
            built = rec.reconstruct(Views(images, colour, depth))
            for level in LEVELS:
                sampler = PaperSampler(level, seed=0)
                for draw in range(2):
                    moved = sampler.sample(i, view=draw).move(colour, 0)[0]
                    t0 = time.thread_time()
                    view = render_view(built, moved, config).rgb
                    t1 = time.thread_time()
                    if way == "registered":  # what a worker adds for the sensor's own map at the new pose
                        in_camera = colour.w2c()[:1] @ sensors.c2w[:1]  # the sensor's pose in its camera's frame
                        render_depth(built, Cameras(sensors.K[:1], moved.c2w @ in_camera, WIDTH, HEIGHT), config)
                        render_ms["colour"].append(t1 - t0)
                        render_ms["sensor_depth"].append(time.thread_time() - t1)
                    scores[(way, level)].append(psnr(view, scene.render(moved)[0]))
        print(f"  scene {i + 1}/{args.scenes}", flush=True)
    rows = {
        way: {
            "median_error_m": round(statistics.mean(e[0] for e in errors[way]), 5),
            "p95_error_m": round(statistics.mean(e[1] for e in errors[way]), 4),
            "coverage": round(statistics.mean(e[2] for e in errors[way]), 4),
            **{f"psnr_{level}": round(statistics.mean(scores[(way, level)]), 2) for level in LEVELS},
        }
        for way in ways
    }  # fmt: skip
    return {
        "quick": args.quick, "scenes": args.scenes, "draws_per_level": 2, "first_seed": FIRST_SEED,
        "frame": [WIDTH, HEIGHT], "colour_focal_px": COLOUR_FOCAL, "depth_focal_px": DEPTH_FOCAL,
        "baseline_m": BASELINE, "register_ms": round(statistics.median(times) * 1e3, 1), "torch_threads": 1,
        "render_ms": {k: round(statistics.median(v) * 1e3, 1) for k, v in render_ms.items()},
        "rows": rows, "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg(),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="one scene")
    parser.add_argument("--scenes", type=int, default=None, help="scenes (default: 4, 1 with --quick)")
    parser.add_argument("--out", type=Path, help=out_help("depth_registration.json"))
    args = parser.parse_args()
    args.out = args.out or default_out("depth_registration.json", args.quick)
    args.scenes = args.scenes or (1 if args.quick else 4)
    result = run(args)
    print(f"register_depth: {result['register_ms']} ms per 640x480 view (one thread)")
    print(f"at a new pose: the colour view {result['render_ms']['colour']} ms, the sensor's depth map "
          f"{result['render_ms']['sensor_depth']} ms more (one thread)")
    print(f"{'depth':>11} {'median err m':>13} {'p95 err m':>10} {'coverage':>9} " +
          " ".join(f"{'PSNR ' + lv:>12}" for lv in LEVELS))  # fmt: skip
    for way, row in result["rows"].items():
        print(f"{way:>11} {row['median_error_m']:>13.4f} {row['p95_error_m']:>10.3f} {row['coverage']:>9.3f} "
              + " ".join(f"{row[f'psnr_{lv}']:>12.2f}" for lv in LEVELS))  # fmt: skip
    write_result(result, args.out)


if __name__ == "__main__":
    main()
