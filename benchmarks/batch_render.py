"""What the training loop spends per batch rendering GenSplat's views after collation
(``render_in="batch"``), against what the workers spend rendering the same draws.

    python benchmarks/batch_render.py [--quick] [--batch-size B] [--size S] [--probability P]
        [--repeats N] [--compiled auto|on|off] [--no-worker] [--profile] [--out results/batch_render.json]

Procedural RGB-D scenes at S x S are cached; B items, each a stack of two frames (Diffusion
Policy's two observation steps) with both external cameras replaced at probability P, are
collated once and moved to the device (CUDA when available). ``render_batch`` then decodes
their depth, moves the cameras, rebuilds the Gaussians and renders and fills every view: on
CUDA in one gsplat call, elsewhere scene by scene with the fast backend. The row is the median
of N timed calls after two warm-up calls (CUDA synchronised; the first call's time, which
includes compiling the disc rule, is reported apart), with the peak GPU memory; ``--compiled``
is render_batch's choice of the compiled disc rule (auto: its default). Beside it (unless
``--no-worker``), the worker path's transform of the same items with the same draws on one CPU thread (what
the dataloader workers would spend on that batch in total, after a first call that compiles
the fast backend). ``--profile`` adds the operators that take one call's device time.
Defaults: batch 64, 224x224, p = 0.5, 10 repeats (batch 4, 32x32, 2 repeats with --quick).
Writes benchmarks/results/batch_render.json (outputs/benchmarks_quick/ with --quick; or --out).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import torch
from machine import cpu_model, default_out, out_help, write_result
from torch.utils.data import Dataset, default_collate

from gensplat_transforms import GenSplatConfig, RGBDReconstructor, SceneCache
from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import GenSplatTransform


class Stacked(Dataset):
    """Items of a :class:`SceneDataset` with each camera's images stacked over the frames
    (f - 1, f) (clamped to the episode), as LeRobot stacks observation steps."""

    def __init__(self, scenes: SceneDataset) -> None:
        self.scenes = scenes

    def __len__(self) -> int:
        return len(self.scenes)

    def __getitem__(self, i: int) -> dict:
        item = self.scenes[i]
        previous = self.scenes[i - 1] if int(item["frame_index"]) > 0 else item
        return {k: torch.stack([previous[k], v]) if k.startswith("observation.images.") else v for k, v in item.items()}


def worker_time(worker_tf: GenSplatTransform, cache: SceneCache, items: list[dict]) -> float:
    """CPU ms on one thread for the worker path's transform of ``items`` with the batch's draws."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    GenSplatTransform(replace(worker_tf.cfg, probability=1.0), cache)(items[0])  # compiles the fast backend
    torch.manual_seed(0)  # the same draws as the batch
    t0 = time.thread_time()
    for item in items:
        worker_tf(item)
    torch.set_num_threads(threads)
    return (time.thread_time() - t0) * 1e3


def top_ops(batch: dict, transform: GenSplatTransform, device: torch.device, options: dict,
            top: int = 15) -> list[dict]:  # fmt: skip
    """The ``top`` operators of one ``render_batch`` call by their own device time (CPU time
    on a CPU), from torch's profiler: where a batch's render time goes."""
    from torch.profiler import ProfilerActivity, profile

    cuda = device.type == "cuda"
    activities = [ProfilerActivity.CPU, *([ProfilerActivity.CUDA] if cuda else [])]
    with profile(activities=activities) as prof:
        render_batch(batch, transform, **options)
        if cuda:
            torch.cuda.synchronize()
    key = "self_device_time_total" if cuda else "self_cpu_time_total"
    ops = sorted(prof.key_averages(), key=lambda e: getattr(e, key), reverse=True)[:top]
    return [{"op": e.key, "calls": e.count, "self_ms": round(getattr(e, key) / 1e3, 3)} for e in ops]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a tiny batch (a smoke run)")
    parser.add_argument("--batch-size", type=int, default=64)
    parser.add_argument("--size", type=int, default=224, help="image height and width")
    parser.add_argument("--probability", type=float, default=0.5)
    parser.add_argument("--repeats", type=int, default=10)
    parser.add_argument("--compiled", choices=("auto", "on", "off"), default="auto",
                        help="render_batch's compiled disc rule (auto: its default, on CUDA)")
    parser.add_argument("--no-worker", action="store_true", help="skip timing the worker path")
    parser.add_argument("--profile", action="store_true", help="also record the ops that take the render's time")
    parser.add_argument("--out", type=Path, help=out_help("batch_render.json"))
    args = parser.parse_args()
    args.out = args.out or default_out("batch_render.json", args.quick)
    if args.quick:
        args.batch_size, args.size, args.repeats = 4, 32, 2
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    source = SceneEpisodes(num_episodes=2, num_frames=8, size=args.size)
    folder = tempfile.TemporaryDirectory()
    cache = SceneCache(folder.name, RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(source.num_episodes), progress=False)
    config = GenSplatConfig(probability=args.probability, cameras=("left", "right"), frame_offsets=(-1, 0))
    batch_tf = GenSplatTransform(replace(config, render_in="batch"), cache)
    worker_tf = GenSplatTransform(replace(config, render_in="worker"), cache)
    data = Stacked(SceneDataset(source))
    order = torch.randint(len(data), (args.batch_size,), generator=torch.Generator().manual_seed(0)).tolist()
    items = [data[i] for i in order]

    torch.manual_seed(0)
    batch = default_collate([batch_tf(item) for item in items])
    batch = {k: v.to(device) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}
    options = {} if args.compiled == "auto" else {"compiled": args.compiled == "on"}
    times = []
    for k in range(args.repeats + 2):
        if device.type == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        render_batch(batch, batch_tf, **options)
        if device.type == "cuda":
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    first_ms, times = times[0], times[2:]
    profile = top_ops(batch, batch_tf, device, options) if args.profile else None
    worker_ms = None if args.no_worker else worker_time(worker_tf, cache, items)
    folder.cleanup()

    augmented = int(batch["gensplat.render"].sum())
    views = augmented * 2 * len(config.replace)
    result = {
        "quick": args.quick, "device": torch.cuda.get_device_name() if device.type == "cuda" else "cpu",
        "batch_size": args.batch_size, "resolution": [args.size, args.size], "stack_frames": 2,
        "cameras_replaced": list(config.replace), "probability": args.probability, "augmented": augmented,
        "views_rendered": views, "compiled": args.compiled, "batch_render_ms": round(statistics.median(times), 2),
        "first_call_ms": round(first_ms, 1),
        "batch_render_runs_ms": [round(t, 2) for t in times],
        "peak_gpu_memory_gb": round(torch.cuda.max_memory_allocated() / 2**30, 2) if device.type == "cuda" else None,
        "worker_ms_one_thread": None if worker_ms is None else round(worker_ms, 1), "profile": profile,
        "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg(),
    }  # fmt: skip
    print(f"batch of {args.batch_size} ({augmented} augmented, {views} views of {args.size}x{args.size}) on "
          f"{result['device']}: {result['batch_render_ms']} ms (first call {first_ms:.0f} ms); the worker path on one "
          f"CPU thread: {result['worker_ms_one_thread']} ms")  # fmt: skip
    write_result(result, args.out)


if __name__ == "__main__":
    main()
