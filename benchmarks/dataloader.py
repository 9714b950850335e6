"""DataLoader throughput with and without GenSplat, where the transform's time goes, and
what the cache costs in bytes and in fidelity.

    python benchmarks/dataloader.py [--quick] [--backend fast] [--replace left right] [--video]
        [--height H --width W] [--episodes N] [--out results/dataloader.json]

A simulated pick-and-place dataset is recorded twice (two external cameras with depth and a
wrist camera; 224x224, 96x96 with --quick, or --height x --width), once with PNG images and
once with MP4 video, for the dataset's own bytes per timestep. On one of them (PNG, or MP4
with --video) the cache is built, and the same DataLoader (same workers, batch size and
sample order) is iterated with and without GenSplat (probability 1, level "train"). The
per-sample split times one worker's steps directly, on one thread, in CPU time of the thread
(``split_ms``, ``transform_ms``; wall time beside it, ``split_wall_ms``, ``transform_wall_ms``,
which other jobs on a shared machine inflate): LeRobot's frame decoding (the dataset's own
cost, apart from GenSplat's), the depth read (from the dataset's depth files,
which the default cache links), rebuilding the Gaussians from the depth and the item's
images, render of the replaced cameras, uint8 conversion, and the whole transform. The
default cache is compared with a compressed copy of the depth (``gensplat cache
--copy-depth``) and with storing the quantised Gaussians themselves (the ``gaussians``
encoding, what a non-depth reconstructor stores) in bytes, and in fidelity: PSNR against
the simulator's true image at perturbed poses, rendered from the cached versus the raw
Gaussians. Writes benchmarks/results/dataloader.json (outputs/benchmarks_quick/dataloader.json
with --quick; or --out); ``resolution`` is [height, width].
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch
from gensplat_lerobot import LeRobotSource, enable_gensplat, prepare, video_backend
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.truth import GroundTruth
from gensplat_sim.world import WorldConfig
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from machine import cpu_model, default_out, out_help, write_result
from torch.utils.data import DataLoader, RandomSampler

from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.geometry import Reconstructor, RGBDReconstructor
from gensplat_transforms.rendering import render
from gensplat_transforms.transform import GenSplatConfig, render_view
from gensplat_transforms.views.perturbation import PaperSampler

REPO = "gensplat/bench_pick_place"


def loader_rate(dataset, workers: int, batch: int, batches: int) -> float:
    """Samples per second over ``batches`` batches (after one warm-up batch)."""
    g = torch.Generator().manual_seed(0)
    sampler = RandomSampler(dataset, replacement=True, num_samples=batch * (batches + 1), generator=g)
    loader = DataLoader(dataset, batch_size=batch, sampler=sampler, num_workers=workers,
                        multiprocessing_context="spawn" if workers else None)  # fmt: skip
    it = iter(loader)
    next(it)
    t0 = time.perf_counter()
    n = sum(next(it)["index"].shape[0] for _ in range(batches))
    return n / (time.perf_counter() - t0)


def split_ms(ds, samples: int, clock=time.thread_time) -> dict:
    """Median per-sample milliseconds of the transform's steps, in this process, by ``clock``
    (default: this thread's CPU time, which other jobs on a shared machine do not inflate)."""
    tf = ds.gensplat
    keys = [tf.cfg.image_key.format(name=n) for n in tf.cfg.cameras]
    times = {k: [] for k in ("frame_decode", "cache_read", "assemble", "render", "to_uint8", "transform_total")}
    for idx in torch.linspace(0, len(ds) - 1, samples).long().tolist():
        t0 = clock()
        item = LeRobotDataset.__getitem__(ds, idx)
        t1 = clock()
        ep, fr = int(item["episode_index"]), int(item["frame_index"])
        images = torch.stack([item[k].float() / 255 if item[k].dtype == torch.uint8 else item[k] for k in keys])
        views = tf.cache._file(ep).depth_views(fr, images)
        t2 = clock()
        rec = tf.cache.reconstructor.assemble(views)
        t3 = clock()
        for name in tf.cfg.replace:
            target = tf.sampler.sample(ep, fr).move(rec.cameras, tf.cfg.cameras.index(name))
            out = render_view(rec, target, tf.cfg)
        t4 = clock()
        (out.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
        t5 = clock()
        tf(item)
        t6 = clock()
        for k, v in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5)):
            times[k].append(v * 1e3)
    return {k: round(statistics.median(v), 2) for k, v in times.items()}


class GaussiansOf(Reconstructor):
    """The same Gaussians, stored as quantised Gaussians (not a DepthReconstructor)."""

    name = "rgbd-gaussians"

    def __init__(self, inner: Reconstructor) -> None:
        self.inner = inner

    def config(self) -> dict:
        return self.inner.config()

    def reconstruct(self, views):
        return self.inner(views)


def cache_fidelity(root: Path, ds, cache: SceneCache, frames: int) -> dict:
    """Mean PSNR against the simulator at Large perturbations: raw vs ``cache``'s Gaussians."""
    source, rgbd, truth = LeRobotSource(root, REPO), RGBDReconstructor(), GroundTruth(root)
    raw_db, cached_db = [], []
    for k, idx in enumerate(torch.linspace(0, len(ds) - 1, frames).long().tolist()):
        item = LeRobotDataset.__getitem__(ds, idx)
        ep, fr = int(item["episode_index"]), int(item["frame_index"])
        views = source.views(ep, fr)
        raw, cached = rgbd(views), cache.read(ep, fr, views.images)
        target = PaperSampler("large", seed=k).sample(ep).move(raw.cameras, 0)
        true_rgb, _ = truth.render(ep, fr, target)
        a = render(raw.gaussians, target, backend="fast")
        b = render(cached.gaussians, target, backend="fast")
        seen = a.alpha > 0.5
        raw_db.append(psnr(a.rgb, true_rgb, seen))
        cached_db.append(psnr(b.rgb, true_rgb, seen))
    raw_mean, cached_mean = statistics.mean(raw_db), statistics.mean(cached_db)
    return {"psnr_raw_db": round(raw_mean, 3), "psnr_cached_db": round(cached_mean, 3),
            "psnr_lost_db": round(raw_mean - cached_mean, 3), "frames": frames}  # fmt: skip


def dataset_bytes_per_timestep(root: Path) -> float:
    """Bytes of the recorded frames (parquet data, videos, images) per timestep, depth excluded."""
    frames = json.loads((root / "meta" / "info.json").read_text())["total_frames"]
    size = sum(f.stat().st_size for d in ("data", "videos", "images") if (root / d).is_dir()
               for f in (root / d).rglob("*") if f.is_file())  # fmt: skip
    return size / frames


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small dataset, few batches (< 1 min)")
    parser.add_argument("--backend", default="fast")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--fill-holes", action=argparse.BooleanOptionalAction, default=True,
                        help="fill uncovered pixels (the transform's default)")
    parser.add_argument("--replace", nargs="+", default=["left", "right"], help="cameras replaced per sample")
    parser.add_argument("--video", action="store_true", help="run on the MP4-encoded recording (default: PNG)")
    parser.add_argument("--height", type=int, default=None, help="image height (default: 224, 96 with --quick)")
    parser.add_argument("--width", type=int, default=None, help="image width (default: 224, 96 with --quick)")
    parser.add_argument("--episodes", type=int, default=None, help="episodes recorded (default: 2, 1 with --quick)")
    parser.add_argument("--out", type=Path, help=out_help("dataloader.json"))
    args = parser.parse_args()
    args.out = args.out or default_out("dataloader.json", args.quick)
    torch.set_num_threads(1)  # as in a dataloader worker
    size, episodes, batches, samples = (96, 1, 3, 4) if args.quick else (224, 2, 10, 12)
    height, width, episodes = args.height or size, args.width or size, args.episodes or episodes
    roots = {}
    for video in (False, True):
        roots[video] = Path(tempfile.mkdtemp()) / "ds"
        record(RecordConfig(roots[video], "pick_place", episodes, seed=0, use_videos=video, repo_id=REPO,
                            world=WorldConfig(width=width, height=height)), progress=False)  # fmt: skip
    root = roots[args.video]
    config = GenSplatConfig(probability=1.0, level="train", backend=args.backend, replace=tuple(args.replace),
                            fill_holes=args.fill_holes)
    t0 = time.perf_counter()
    stats = prepare(root, REPO, config, progress=False)
    build_s = time.perf_counter() - t0
    frames = sum(s.num_frames for s in stats.values())
    source = LeRobotSource(root, REPO)
    gaussians = SceneCache(Path(tempfile.mkdtemp()), GaussiansOf(RGBDReconstructor()), source.fingerprint)
    gaussian_bytes = sum(gaussians.ensure(ep, source).bytes for ep in stats)
    copy = SceneCache(Path(tempfile.mkdtemp()), RGBDReconstructor(), source.fingerprint, link_depth=False)
    copy_bytes = sum(copy.ensure(ep, source).bytes for ep in stats)

    plain = LeRobotDataset(REPO, root=root, video_backend=video_backend())
    gensplat = enable_gensplat(LeRobotDataset(REPO, root=root, video_backend=video_backend()))
    split_ms(gensplat, samples)  # warm-up: this process's first reads of the files and first calls
    split = split_ms(gensplat, samples)
    wall = split_ms(gensplat, samples, time.perf_counter)
    result = {
        "quick": args.quick, "backend": args.backend, "workers": args.workers, "resolution": [height, width],
        "episodes": episodes,
        "fill_holes": args.fill_holes,
        "cameras_reconstructed": list(config.cameras), "cameras_replaced": list(config.replace),
        "samples_per_s_plain": round(loader_rate(plain, args.workers, 4, batches), 2),
        "samples_per_s_gensplat": round(loader_rate(gensplat, args.workers, 4, batches), 2),
        "transform_ms": split["transform_total"], "split_ms": split,
        "transform_wall_ms": wall["transform_total"], "split_wall_ms": wall,
        "video": args.video,
        "cache_bytes_per_timestep": round(sum(s.bytes for s in stats.values()) / frames),
        "copied_depth_bytes_per_timestep": round(copy_bytes / frames),
        "gaussians_encoding_bytes_per_timestep": round(gaussian_bytes / frames),
        "dataset_bytes_per_timestep": {"png": round(dataset_bytes_per_timestep(roots[False])),
                                       "mp4": round(dataset_bytes_per_timestep(roots[True]))},
        "cache_build_ms_per_timestep": round(build_s / frames * 1e3, 1),
        "cache_fidelity": cache_fidelity(root, gensplat, gensplat.gensplat.cache, samples // 2),
        "copied_depth_fidelity": cache_fidelity(root, gensplat, copy, samples // 2),
        "machine": {"cpus": os.cpu_count(), **cpu_model()},
        "load_average": os.getloadavg(),
    }  # fmt: skip
    for k in ("samples_per_s_plain", "samples_per_s_gensplat", "transform_ms", "cache_bytes_per_timestep",
              "copied_depth_bytes_per_timestep", "gaussians_encoding_bytes_per_timestep",
              "cache_build_ms_per_timestep"):  # fmt: skip
        print(f"{k:30}{result[k]:>12}")
    copied = {f"copied_depth_{k}": v for k, v in result["copied_depth_fidelity"].items()}
    for k, v in {**split, **result["cache_fidelity"], **copied, **result["dataset_bytes_per_timestep"]}.items():
        print(f"  {k:28}{v:>12}")
    write_result(result, args.out)


if __name__ == "__main__":
    main()
