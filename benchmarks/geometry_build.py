"""What batching timesteps gains a geometry cache build: ``GeometryReconstructor.predict_depths``
(the model's forward pass and each timestep's depth, cameras and copy to the CPU, as a
cache build runs it) at several ``batch_timesteps``, on CUDA.

    python benchmarks/geometry_build.py [--out FILE]     # CUDA: the full configuration, ~1 min on an H200
    python benchmarks/geometry_build.py --quick          # smoke run: small configuration, tiny images, CPU too

The full configuration (Pi3's size, about 0.96 B parameters) is built with random weights
(the time does not depend on them) and runs under bfloat16 autocast on two calibrated views
of random images at DROID's size (180x320, run at 182x322) and at 294x518, for
``batch_timesteps`` 1, 8, 32, 64 and automatic (None). A given batch is capped so that no
tensor reaches 2**31 elements (``effective``). Each row: one warm-up pass at its batch size,
then two batches' worth of timesteps (at least 16), CUDA synchronised; ms per timestep,
timesteps/s and the peak GPU memory. A row that fails (e.g. out of memory) records its error
instead. Writes benchmarks/results/geometry_build_<gpu>.json (``--quick``:
outputs/benchmarks_quick/geometry_build_<gpu or cpu>_quick.json; or ``--out``).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import default_out, out_help

from gensplat_transforms.data.scenes import default_cameras
from gensplat_transforms.geometry import GeometryReconstructor, Views
from gensplat_transforms.geometry.model import GenSplatModel, ModelConfig

SIZES = ("180x320", "294x518")  # height x width of the input; DROID's runs at 182x322
BATCHES = ("1", "8", "32", "64", "auto")


def time_row(rec: GeometryReconstructor, height: int, width: int, batch: int | None, device: str,
             min_steps: int = 16) -> dict:
    """One row: ``rec`` at ``batch`` timesteps per pass (None: automatic) on random two-view timesteps."""
    rec.batch_timesteps = batch  # the attribute predict_depths reads (the constructor only checks it)
    effective = rec.timesteps_per_pass(2, height, width)
    row = {"size": f"{height}x{width}", "batch_timesteps": batch if batch is not None else "auto",
           "effective": effective, "timesteps": max(2 * effective, min_steps)}  # fmt: skip
    cams = default_cameras(width, height)[:2]
    gen = torch.Generator().manual_seed(0)
    views = [Views(torch.rand(2, 3, height, width, generator=gen), cams) for _ in range(min(row["timesteps"], 4))]
    views = [views[t % len(views)] for t in range(row["timesteps"])]  # the content does not change the time
    try:
        list(rec.predict_depths(views[:effective]))  # warm-up at this batch size
        if device == "cuda":
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
        start = time.perf_counter()
        out = list(rec.predict_depths(views))
        if device == "cuda":
            torch.cuda.synchronize()
        seconds = time.perf_counter() - start
        assert len(out) == len(views) and all(torch.isfinite(o.depths).all() for o in out[:1])
        row |= {"ms_per_timestep": round(1e3 * seconds / len(views), 2),
                "timesteps_per_s": round(len(views) / seconds, 1), "model_size": list(out[0].depths.shape[-2:])}  # fmt: skip
        if device == "cuda":
            row["peak_gpu_gb"] = round(torch.cuda.max_memory_allocated() / 2**30, 2)
    except Exception as e:  # noqa: BLE001 -- a failing batch size is a result
        row["error"] = f"{type(e).__name__}: {e}"[:400]
    finally:
        if device == "cuda":
            torch.cuda.empty_cache()
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small configuration at 28x42, batches 1 2 auto, a few timesteps (CPU too)")
    parser.add_argument("--sizes", nargs="+", default=None, help="HEIGHTxWIDTH inputs (default: 180x320 294x518)")
    parser.add_argument("--batches", nargs="+", default=None, help="batch_timesteps values or auto (default: "
                                                                      "1 8 32 64 auto; --quick: 1 2 auto)")
    parser.add_argument("--out", default=None, help=out_help("geometry_build_<gpu>[_quick].json"))
    args = parser.parse_args()
    device = "cuda" if torch.cuda.is_available() else "cpu"
    if device == "cpu" and not args.quick:
        print("geometry_build: no CUDA; the full configuration on the CPU takes far too long (use --quick)")
        return 2
    sizes = args.sizes or (("28x42",) if args.quick else SIZES)
    batches = args.batches or (("1", "2", "auto") if args.quick else BATCHES)
    torch.manual_seed(0)
    config = ModelConfig.small() if args.quick else ModelConfig.full()
    with torch.device(device):  # random weights, initialised where they run
        model = GenSplatModel(config).eval()
    dtype = torch.bfloat16 if device == "cuda" else None
    rec = GeometryReconstructor(model, device=device, autocast_dtype=dtype)
    rows = []
    for size in sizes:
        height, width = map(int, size.split("x"))
        for b in batches:
            rows.append(time_row(rec, height, width, None if b == "auto" else int(b), device, 4 if args.quick else 16))
            print(rows[-1], flush=True)

    print(f"\n{'size':>9}{'batch':>7}{'eff.':>6}{'steps':>7}{'ms/step':>10}{'steps/s':>9}{'peak GB':>9}  error")
    for r in rows:
        print(f"{r['size']:>9}{r['batch_timesteps']!s:>7}{r['effective']:>6}{r['timesteps']:>7}"
              f"{r.get('ms_per_timestep', '-')!s:>10}{r.get('timesteps_per_s', '-')!s:>9}"
              f"{r.get('peak_gpu_gb', '-')!s:>9}  {r.get('error', '')}")  # fmt: skip
    gpu = torch.cuda.get_device_name() if device == "cuda" else None
    name = re.sub(r"[^a-z0-9]+", "_", (gpu or "cpu").lower()).strip("_") + ("_quick" if args.quick else "")
    out = Path(args.out) if args.out else default_out(f"geometry_build_{name}.json", args.quick)
    result = {"rows": rows, "gpu": gpu, "device": device, "torch": torch.__version__,
              "config": "small" if args.quick else "full", "views": 2, "autocast": str(dtype) if dtype else None,
              "parameters_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 1)}  # fmt: skip
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print("wrote", out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
