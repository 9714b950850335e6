"""Render speed of the "fast" CPU backend on the standard scene, against the reference.

Usage: python benchmarks/render_speed.py [--quick] [--avx2] [--out PATH]

Times ``render(..., backend="fast", threads=n)`` for n = 1 and 2 (median of repeated
frames after warm-up), the backend alone with its time split (projection / binning /
raster), and the pure-PyTorch reference once per frame setting; checks the fast image
against the reference (PSNR, depth error where alpha > 0.5). torch runs on one thread, as
in a dataloader worker. Where CUDA and gsplat are present it also times the "gsplat"
backend (``gsplat`` in the JSON: the Gaussians resident on the GPU, and uploaded per frame)
against the fast image; elsewhere ``gsplat.available`` is false with the reason. Prints a
table and writes benchmarks/results/render_speed.json (``--out`` to write elsewhere; ``--quick``:
outputs/benchmarks_quick/render_speed.json).
The machine may be shared: figures are medians, and min/max are recorded beside them.

``--avx2`` compiles the fast backend for this CPU with its AVX-512 features off (numba's
``NUMBA_CPU_FEATURES``; compiled code is cached per feature set), so that one core measures
what the vector width alone costs: an AVX-512 machine then runs the code an AVX2-only CPU
would get (``codegen`` in the JSON).

OpenMP threads sleep between parallel regions here (OMP_WAIT_POLICY=PASSIVE unless set):
with the default busy-waiting, numba's idle worker threads took the second core from the
main thread and from torch, making 2-thread frames and torch's checks many times slower
on this 2-core machine (see the fast backend's docstring).
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch and numba load OpenMP
sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import avx2_features, cpu_model, default_out, out_help

if "--avx2" in sys.argv:  # before numba reads its configuration
    os.environ["NUMBA_CPU_FEATURES"] = avx2_features()

import numba
import torch
from standard_scene import standard_scene

from gensplat_transforms import render
from gensplat_transforms.rendering import DILATION, project
from gensplat_transforms.rendering.fast import render_fast


def _codegen() -> str:
    """What numba compiles for: "native", "avx2 (AVX-512 off)" or the user's feature string."""
    return "avx2 (AVX-512 off)" if "--avx2" in sys.argv else os.environ.get("NUMBA_CPU_FEATURES") or "native"


def _time(fn, repeats: int, clock=time.perf_counter) -> list[float]:
    """Milliseconds of ``repeats`` calls, by ``clock``."""
    out = []
    for _ in range(repeats):
        start = clock()
        fn()
        out.append((clock() - start) * 1e3)
    return out


def _stats(ms: list[float]) -> dict:
    return {"median": statistics.median(ms), "min": min(ms), "max": max(ms), "n": len(ms)}


def _backend_split(scene, threads: int, repeats: int) -> dict:
    """Median ms of each backend stage (render_fast called directly, no API overhead)."""
    bg = torch.zeros(3)
    rows = []
    for _ in range(repeats):
        t = {}
        start = time.perf_counter()
        render_fast(scene.gaussians, scene.target, background=bg, near=0.01, sh_degree=None,
                    out_dtype=torch.float32, return_depth=True, dilation=DILATION, threads=threads, timings=t)  # fmt: skip
        t["total"] = (time.perf_counter() - start) * 1e3
        rows.append(t)
    return {k: statistics.median(r[k] for r in rows) for k in ("projection", "binning", "raster", "total")}


def _accuracy(fast, ref) -> dict:
    mse = (fast.rgb - ref.rgb).square().mean().item()
    solid = ref.alpha > 0.5
    rel = ((fast.depth - ref.depth).abs() / ref.depth.abs().clamp_min(1e-12))[solid]
    return {
        "psnr_vs_reference_db": 10 * math.log10(1.0 / mse) if mse > 0 else float("inf"),
        "rgb_max_abs_err": (fast.rgb - ref.rgb).abs().max().item(),
        "alpha_max_abs_err": (fast.alpha - ref.alpha).abs().max().item(),
        "depth_max_rel_err": rel.max().item() if rel.numel() else 0.0,
    }


def _gsplat(scene, fast, repeats: int) -> dict:
    """The gsplat backend on CUDA: median ms per frame with the Gaussians already on the GPU
    and with them uploaded from the CPU each frame, and agreement with the fast image."""
    try:
        out = render(scene.gaussians, scene.target, backend="gsplat")
    except RuntimeError as e:  # no CUDA device, or gsplat missing: render says which
        return {"available": False, "reason": str(e)}
    cuda = scene.gaussians.to(torch.device("cuda"))

    def timed(gaussians) -> float:
        def frame():
            render(gaussians, scene.target, backend="gsplat")
            torch.cuda.synchronize()

        _time(frame, 5)  # warm-up
        return statistics.median(_time(frame, repeats))

    accuracy = _accuracy(out, fast)
    return {
        "available": True,
        "device": torch.cuda.get_device_name(),
        "ms_resident": timed(cuda),
        "ms_with_upload": timed(scene.gaussians),
        "psnr_vs_fast_db": accuracy["psnr_vs_reference_db"],
        "alpha_max_abs_err_vs_fast": accuracy["alpha_max_abs_err"],
        "depth_max_rel_err_vs_fast": accuracy["depth_max_rel_err"],
    }


def _scene_stats(scene) -> dict:
    proj = project(scene.gaussians, scene.target)
    b = proj.boxes
    t = b >> 4  # the 16x16 tiles of the fast backend
    return {
        "num_gaussians": len(scene.gaussians),
        "visible_splats": len(proj),
        "box_pairs": int(((b[:, 2] - b[:, 0] + 1) * (b[:, 3] - b[:, 1] + 1)).sum()),
        # (splat, tile) pairs: the entries of the fast backend's tile lists
        "box_tile_pairs": int(((t[:, 2] - t[:, 0] + 1) * (t[:, 3] - t[:, 1] + 1)).sum()),
    }


def run(quick: bool) -> dict:
    torch.set_num_threads(1)
    repeats = 7 if quick else 30
    load_before = os.getloadavg()[0]

    start = time.perf_counter()
    scene = standard_scene()
    build_s = time.perf_counter() - start
    target = scene.target

    start = time.perf_counter()
    fast = render(scene.gaussians, target, backend="fast")
    first_call_s = time.perf_counter() - start  # numba cache load (or compilation) + one frame

    ref_ms = _time(lambda: render(scene.gaussians, target, backend="reference"), 1 if quick else 3)
    ref = render(scene.gaussians, target, backend="reference")
    accuracy = _accuracy(fast, ref)

    api, split = {}, {}
    for threads in (1, 2):
        frame = functools.partial(render, scene.gaussians, target, backend="fast", threads=threads)
        _time(frame, 3)  # warm-up
        api[threads] = _stats(_time(frame, repeats))
        # CPU time of this process: less sensitive to other processes on a shared machine
        api[threads]["cpu_median"] = statistics.median(_time(frame, repeats, time.process_time))
        split[threads] = _backend_split(scene, threads, repeats)
        assert torch.equal(render(scene.gaussians, target, backend="fast", threads=threads).rgb, fast.rgb)

    light = standard_scene(sigma_px=0.4)  # RGB-D-sized splats (the default discs are 0.3 px: lighter still)
    light_ms = {}
    for threads in (1, 2):
        frame = functools.partial(render, light.gaussians, light.target, backend="fast", threads=threads)
        _time(frame, 3)
        light_ms[threads] = statistics.median(_time(frame, repeats))

    reference_ms = statistics.median(ref_ms)
    gsplat = _gsplat(scene, fast, repeats)
    return {
        "ms_1thread": api[1]["median"],
        "ms_2threads": api[2]["median"],
        "cpu_ms_1thread": api[1]["cpu_median"],
        "reference_ms": reference_ms,
        "speedup_1thread": reference_ms / api[1]["median"],
        "speedup_2threads": reference_ms / api[2]["median"],
        **accuracy,
        **_scene_stats(scene),
        "resolution": [target.height, target.width],
        "sh_degree": scene.gaussians.sh_degree,
        "time_split_ms": {
            f"{t}thread{'s' if t > 1 else ''}": {k: round(v, 3) for k, v in split[t].items()} for t in (1, 2)
        },
        "render_api_ms": {f"{t}": {k: round(v, 3) for k, v in api[t].items()} for t in (1, 2)},
        "light_scene_sigma_px_0.4": {
            **_scene_stats(light), "ms_1thread": light_ms[1], "ms_2threads": light_ms[2],
        },
        "gsplat": gsplat,
        "codegen": _codegen(),
        "first_call_s": first_call_s,
        "scene_build_s": build_s,
        "quick": quick,
        "repeats": repeats,
        "machine": {
            "cpus": os.cpu_count(),
            "processor": platform.processor() or platform.machine(),
            **cpu_model(),
            "numba": numba.__version__,
            "numba_threading_layer": numba.threading_layer(),
            "torch_threads": torch.get_num_threads(),
            "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY"),
            "load_average_before_after": [load_before, os.getloadavg()[0]],
        },
    }


def _split(t: dict) -> str:
    parts = f"proj {t['projection']:.1f} + bin {t['binning']:.1f} + raster {t['raster']:.1f}"
    return f"{parts} = {t['total']:.1f} ms"


def _print_table(r: dict) -> None:
    s1, s2 = r["time_split_ms"]["1thread"], r["time_split_ms"]["2threads"]
    light, m = r["light_scene_sigma_px_0.4"], r["machine"]
    rows = [
        ("Gaussians / visible splats", f"{r['num_gaussians']} / {r['visible_splats']}"),
        ("(splat, pixel) pairs in boxes", f"{r['box_pairs'] / 1e6:.1f} M"),
        ("(splat, tile) pairs in boxes", f"{r['box_tile_pairs'] / 1e3:.0f} k"),
        ("resolution", "x".join(map(str, r["resolution"]))),
        ("CPU (family/model), SIMD", f"{m.get('cpu_model')} ({m.get('cpu_family_model')}), {m.get('simd')}"),
        ("compiled for", r["codegen"]),
        ("fast, 1 thread (render())", f"{r['ms_1thread']:.1f} ms (CPU time {r['cpu_ms_1thread']:.1f} ms)"),
        ("fast, 2 threads (render())", f"{r['ms_2threads']:.1f} ms"),
        ("  backend split, 1 thread", _split(s1)),
        ("  backend split, 2 threads", _split(s2)),
        ("reference (pure PyTorch, 1 thread)", f"{r['reference_ms']:.0f} ms"),
        ("speed-up, 1 / 2 threads", f"{r['speedup_1thread']:.0f}x / {r['speedup_2threads']:.0f}x"),
        ("PSNR vs reference", f"{r['psnr_vs_reference_db']:.1f} dB"),
        ("rgb / alpha max abs error", f"{r['rgb_max_abs_err']:.1e} / {r['alpha_max_abs_err']:.1e}"),
        ("depth max rel error (alpha > 0.5)", f"{r['depth_max_rel_err']:.1e}"),
        ("light scene (sigma 0.4 px), 1 / 2 threads",
         f"{light['ms_1thread']:.1f} / {light['ms_2threads']:.1f} ms"),
        ("first call (cache load or compile)", f"{r['first_call_s']:.2f} s"),
    ]
    g = r["gsplat"]
    if g["available"]:
        rows += [
            (
                f"gsplat on {g['device']}, resident / upload",
                f"{g['ms_resident']:.2f} / {g['ms_with_upload']:.2f} ms",
            ),
            ("gsplat PSNR vs fast", f"{g['psnr_vs_fast_db']:.1f} dB"),
        ]
    else:
        rows.append(("gsplat backend", "not measured: " + g["reason"]))
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"{k:<{width}}  {v}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (under a minute)")
    parser.add_argument("--avx2", action="store_true", help="compile for this CPU without AVX-512")
    parser.add_argument("--out", type=Path, help=out_help("render_speed.json"))
    args = parser.parse_args()
    args.out = args.out or default_out("render_speed.json", args.quick)
    result = run(args.quick)
    _print_table(result)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
