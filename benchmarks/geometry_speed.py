"""Time per timestep of the geometry path (two views) for the small and the full (Pi3-size)
model configurations, on this machine's CPU (and CUDA when available).

    python benchmarks/geometry_speed.py [--quick] [--size 224] [--repeats 3] [--configs small full]
        [--out FILE]

The full configuration is built with random weights (Pi3's weights are not downloadable
here; the time does not depend on the values): DINOv2 ViT-L/14 encoder, 36 decoder blocks,
about 0.96 B parameters. Each row times ``GeometryReconstructor.predict_depth`` (the
model's forward pass and the depth extraction) and ``assemble`` (the RGB-D discs) on two
views of the built-in tabletop. Writes benchmarks/results/geometry_speed.json (or ``--out``).
``--quick`` is a smoke run whose figures mean little: the small configuration at 56x56, one timed
run, written to outputs/benchmarks_quick/geometry_speed.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry import GeometryReconstructor, Views
from gensplat_transforms.geometry.model import GenSplatModel, ModelConfig


def time_config(name: str, size: int, repeats: int, device: str, threads: int) -> dict:
    torch.manual_seed(0)
    config = ModelConfig.full() if name == "full" else ModelConfig.small()
    model = GenSplatModel(config).eval()
    rec = GeometryReconstructor(model, device=device)
    cams = default_cameras(size, size)
    images, _ = TabletopScene(0).render(cams)
    views = Views(images[:2], cams[:2])
    rec.assemble(rec.predict_depth(views))  # warm-up (and numba's compiled-code cache)
    predict, assemble = [], []
    for _ in range(repeats):
        t0 = time.perf_counter()
        depth = rec.predict_depth(views)
        if device == "cuda":
            torch.cuda.synchronize()
        t1 = time.perf_counter()
        rec.assemble(depth)
        predict.append(t1 - t0)
        assemble.append(time.perf_counter() - t1)
    return {"config": name, "device": device, "threads": threads, "size": size,
            "parameters_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 1),
            "predict_depth_s": round(statistics.median(predict), 3),
            "assemble_ms": round(statistics.median(assemble) * 1e3, 1), "repeats": repeats}  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: small configuration, 56x56, once")
    parser.add_argument("--size", type=int, default=224, help="image side in pixels (default: 224)")
    parser.add_argument("--repeats", type=int, default=3, help="timed runs per row after a warm-up (default: 3)")
    parser.add_argument("--configs", nargs="+", default=["small", "full"], choices=["small", "full"])
    parser.add_argument("--threads", type=int, default=os.cpu_count(), help="torch CPU threads (default: all)")
    parser.add_argument("--out", type=Path, help=out_help("geometry_speed.json"))
    args = parser.parse_args()
    if args.quick:
        args.size, args.repeats, args.configs = 56, 1, ["small"]
    torch.set_num_threads(args.threads)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    if "cuda" not in devices:
        print("geometry_speed: no CUDA device (torch.cuda.is_available() is False): CPU rows only")
    rows = [time_config(c, args.size, args.repeats, d, args.threads) for d in devices for c in args.configs]
    print(f"{'config':8}{'device':8}{'params (M)':>12}{'predict_depth (s)':>20}{'assemble (ms)':>16}")
    for r in rows:
        print(f"{r['config']:8}{r['device']:8}{r['parameters_m']:>12}{r['predict_depth_s']:>20}{r['assemble_ms']:>16}")
    result = {"quick": args.quick, "rows": rows,
              "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
              "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg()}  # fmt: skip
    write_result(result, args.out or default_out("geometry_speed.json", args.quick))


if __name__ == "__main__":
    main()
