"""Accuracy costs time: PSNR and SSIM against the full-quality render versus milliseconds.

Usage: python benchmarks/accuracy_vs_time.py [--quick] [--out DIR]

On the standard scene (``standard_scene.py``), the full-quality render is the "fast" backend
with every Gaussian (stride 1), SH degree 3, float32 storage, at 224x224. One knob at a time
departs from it:

* ``resolution``: rendered at s x s (intrinsics scaled) and resized to 224x224 (bilinear,
  antialiased when shrinking), compared with the full-quality 224 render;
* ``density``: Gaussians re-reconstructed with ``RGBDReconstructor(stride=s)`` (1/s^2 of the
  Gaussians per source view, splats s times wider; the small random higher-order SH of the
  standard scene is redrawn for the new count);
* ``sh_degree``: colour evaluated up to degree 0..3;
* ``prune``: ``Gaussians.prune(t)`` (the standard scene's opacities are 0.85..0.95, so only
  thresholds above 0.85 remove any);
* ``storage``: float16 Gaussians, and the cache's quantised form (``cache.quantize`` in the
  scene's bounding box, then ``dequantize``, whose time is included);
* ``backend``: the pure-PyTorch reference against the fast backend.

Times are medians of repeated frames after a warm-up, one thread for torch and numba
(``threads=1``), as in a dataloader worker: wall-clock ``ms`` and process CPU time
``cpu_ms``. The machine may be shared: settings are timed in interleaved rounds so that load
changes touch them alike, and the load average is recorded. Prints a table, writes
accuracy_vs_time.json and .png into ``--out`` (default benchmarks/results/;
outputs/benchmarks_quick/ with ``--quick``).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as in render_speed.py

import numpy as np
import torch
import torch.nn.functional as F

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import default_out, out_help
from plotting import Panel, line_panels
from standard_scene import standard_scene

from gensplat_transforms import render
from gensplat_transforms.cache.store import dequantize, quantize
from gensplat_transforms.core.metrics import psnr, ssim

SIZE = 224
PLOT_MAX_DB = 60.0
COLOURS = {"resolution": (31, 119, 180), "density": (255, 127, 14), "sh_degree": (44, 160, 44),
           "prune": (214, 39, 40), "storage": (148, 103, 189), "backend": (140, 86, 75)}  # fmt: skip


def to_full_size(rgb: torch.Tensor) -> torch.Tensor:
    """(1, 3, s, s) render -> (1, 3, 224, 224), bilinear, antialiased when shrinking."""
    if rgb.shape[-1] == SIZE:
        return rgb
    return F.interpolate(rgb, size=(SIZE, SIZE), mode="bilinear", align_corners=False, antialias=True)


def settings(scene, quick: bool) -> list[tuple[str, str, dict]]:
    """(knob, setting, spec) rows; a spec holds ``render`` keyword arguments (the Gaussians
    may be replaced by ``prepare``, a timed step that produces them)."""
    g, cam = scene.gaussians, scene.target
    fast = {"gaussians": g, "cameras": cam, "backend": "fast", "threads": 1}
    rows = [("resolution", str(s), {**fast, "cameras": cam.resize(s, s)}) for s in (112, 160, 224, 320)]
    for stride in (1, 2, 4):
        dense = g if stride == 1 else standard_scene(SIZE, stride=stride).gaussians
        rows.append(("density", f"1/{stride * stride}", {**fast, "gaussians": dense}))
    rows += [("sh_degree", str(d), {**fast, "sh_degree": d}) for d in range(4)]
    rows += [("prune", str(t), {**fast, "gaussians": g.prune(t)}) for t in (0.0, 0.05, 0.2, 0.5, 0.9)]
    lo, hi = g.means.amin(0), g.means.amax(0)
    q = quantize(g, lo, hi)
    rows += [
        ("storage", "fp32", fast),
        ("storage", "fp16", {**fast, "gaussians": g.to(dtype=torch.float16)}),
        ("storage", "quantized", {**fast, "prepare": lambda: dequantize(q, lo, hi)}),
        ("backend", "fast", fast),
    ]
    if not quick:  # the reference takes seconds per frame
        rows.append(("backend", "reference", {"gaussians": g, "cameras": cam, "backend": "reference"}))
    return rows


def frame_fn(spec: dict):
    """A function rendering one setting: () -> ((1, 3, H, W) image, number of Gaussians)."""
    spec = dict(spec)
    prepare = spec.pop("prepare", None)

    def frame() -> tuple[torch.Tensor, int]:
        g = prepare() if prepare else spec["gaussians"]
        return render(**{**spec, "gaussians": g}, return_depth=False, return_alpha=False).rgb, len(g)

    return frame


def run(quick: bool) -> dict:
    """Time every setting in interleaved rounds (so that a change of machine load touches
    all settings alike; the reference joins the first 3 rounds only) and score its image."""
    torch.set_num_threads(1)
    start, load_before = time.perf_counter(), os.getloadavg()
    scene = standard_scene(SIZE)
    repeats = 3 if quick else 21
    full = render(scene.gaussians, scene.target, backend="fast", threads=1, return_depth=False).rgb
    full = full.clamp(0, 1)
    rows = settings(scene, quick)
    frames = [frame_fn(spec) for _, _, spec in rows]
    outputs = [f() for f in frames]  # warm-up, and the images to score
    wall: list[list[float]] = [[] for _ in rows]
    cpu: list[list[float]] = [[] for _ in rows]
    for r in range(repeats):
        for i, (_, _, spec) in enumerate(rows):
            if spec["backend"] == "reference" and r >= 3:
                continue
            w0, c0 = time.perf_counter(), time.process_time()
            frames[i]()
            wall[i].append((time.perf_counter() - w0) * 1e3)
            cpu[i].append((time.process_time() - c0) * 1e3)
    table = []
    for (knob, setting, _), (rgb, n), w, c in zip(rows, outputs, wall, cpu):
        rgb = to_full_size(rgb).clamp(0, 1)
        db = psnr(rgb, full)
        table.append({"knob": knob, "setting": setting, "ms": round(statistics.median(w), 2),
                      "cpu_ms": round(statistics.median(c), 2), "ms_min": round(min(w), 2),
                      "psnr_db": round(db, 2) if math.isfinite(db) else None,  # None: identical
                      "ssim": round(ssim(rgb, full), 5), "num_gaussians": n, "runs": len(w)})  # fmt: skip
    return {
        "rows": table,
        "settings": {
            "quick": quick, "scene": "benchmarks/standard_scene.py", "full_quality": (
                "fast backend, stride 1 (all Gaussians), SH degree 3, float32, 224x224"),
            "resolution_comparison": "rendered at s x s, resized to 224 (bilinear, antialiased), vs the 224 render",
            "density": "re-reconstructed with RGBDReconstructor(stride=s)", "torch_threads": 1,
            "fast_threads": 1, "repeats": repeats,
            "timing": "medians over interleaved rounds after one warm-up frame; ms wall, cpu_ms process CPU time",
            "quantized_ms": "includes dequantize", "psnr_null": "identical to the full-quality render",
            "loadavg_1_5_15_before": [round(x, 2) for x in load_before],
            "loadavg_1_5_15_after": [round(x, 2) for x in os.getloadavg()],
            "cpu_count": os.cpu_count(), "seconds": round(time.perf_counter() - start, 1),
        },
    }  # fmt: skip


def plot(rows: list[dict], path: Path) -> None:
    """PSNR and SSIM against milliseconds (log axis), one line per knob through its settings
    in order; every setting but the full-quality one is labelled."""
    ms = [r["ms"] for r in rows]
    x_lo, x_hi = math.floor(math.log10(min(ms)) * 4) / 4, math.ceil(math.log10(max(ms)) * 4) / 4
    x_ticks = [(math.log10(t), f"{t:g} ms") for t in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000)
               if x_lo <= math.log10(t) <= x_hi]  # fmt: skip
    ssims = [r["ssim"] for r in rows]
    s_lo = math.floor(min(ssims) * 20) / 20
    db_lo = 5 * math.floor(min(r["psnr_db"] for r in rows if r["psnr_db"] is not None) / 5)

    def series(key: str, cap: float) -> dict:
        out: dict = {}
        for r in rows:
            value = cap if r[key] is None else r[key]
            label = "" if r["psnr_db"] is None else r["setting"]  # the full-quality setting: no label
            out.setdefault(r["knob"], []).append((math.log10(r["ms"]), value, label))
        return out

    panels = [
        Panel("PSNR vs full quality (dB)", series("psnr_db", PLOT_MAX_DB), (x_lo, x_hi), (db_lo, PLOT_MAX_DB),
              x_ticks, [(t, f"{t:.0f}") for t in np.arange(db_lo, PLOT_MAX_DB + 1e-9, 5)]),
        Panel("SSIM vs full quality", series("ssim", 1.0), (x_lo, x_hi), (s_lo, 1.0),
              x_ticks, [(t, f"{t:.2f}") for t in np.arange(s_lo, 1.0 + 1e-9, 0.05)]),
    ]  # fmt: skip
    note = (f"ms per 224x224 frame, 1 thread (log axis); PSNR above {PLOT_MAX_DB:.0f} dB "
            f"(or identical images) is drawn at {PLOT_MAX_DB:.0f}.")  # fmt: skip
    line_panels(path, panels, {k: COLOURS[k] for k in dict.fromkeys(r["knob"] for r in rows)}, note,
                panel_size=(520, 360))  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="3 repeats, no reference backend (< 1 min)")
    parser.add_argument("--out", type=Path, help=out_help(""))
    args = parser.parse_args()
    args.out = args.out or default_out("", args.quick)
    result = run(args.quick)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "accuracy_vs_time.json").write_text(json.dumps(result, indent=2, allow_nan=False) + "\n")
    plot(result["rows"], args.out / "accuracy_vs_time.png")
    print(f"{'knob':>10} {'setting':>9} {'ms':>8} {'cpu ms':>8} {'PSNR dB':>8} {'SSIM':>7} {'Gaussians':>9}")
    for r in result["rows"]:
        db = "exact" if r["psnr_db"] is None else f"{r['psnr_db']:.2f}"
        print(f"{r['knob']:>10} {r['setting']:>9} {r['ms']:8.1f} {r['cpu_ms']:8.1f} {db:>8} "
              f"{r['ssim']:7.4f} {r['num_gaussians']:9d}")  # fmt: skip
    s = result["settings"]
    print(f"load average before {s['loadavg_1_5_15_before']}, after {s['loadavg_1_5_15_after']}; "
          f"wrote {args.out / 'accuracy_vs_time.json'} and .png ({s['seconds']} s)")  # fmt: skip


if __name__ == "__main__":
    main()
