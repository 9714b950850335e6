"""DataLoader throughput with and without GenSplat, and where the transform's time goes.

    python benchmarks/dataloader.py [--quick] [--backend fast]

A local LeRobot dataset of the built-in procedural scene (two external cameras with depth
plus a third camera, 224x224) is recorded, its Gaussian cache built, and the same
DataLoader (same workers, batch size, order) is iterated with and without GenSplat
(probability 1, level "train"). The per-sample split times one worker's steps directly:
cache read, render, resize and dtype conversion. Writes benchmarks/results/dataloader.json.
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

import torch  # noqa: E402
from lerobot.datasets.lerobot_dataset import LeRobotDataset  # noqa: E402
from torch.utils.data import DataLoader, RandomSampler  # noqa: E402

from gensplat_lerobot import enable_gensplat, prepare  # noqa: E402
from gensplat_lerobot.record import record_scene_dataset  # noqa: E402
from gensplat_transforms.episodes import SceneEpisodes  # noqa: E402
from gensplat_transforms.perturbation import pivot_point  # noqa: E402
from gensplat_transforms.rendering import render  # noqa: E402
from gensplat_transforms.transform import GenSplatConfig  # noqa: E402

REPO = "local/gensplat_bench"


def loader_rate(dataset, workers: int, batch: int, batches: int) -> float:
    """Samples per second over ``batches`` batches (after one warm-up batch)."""
    g = torch.Generator().manual_seed(0)
    sampler = RandomSampler(dataset, replacement=True, num_samples=batch * (batches + 1), generator=g)
    loader = DataLoader(dataset, batch_size=batch, sampler=sampler, num_workers=workers,
                        multiprocessing_context="spawn" if workers else None)  # fmt: skip
    it = iter(loader)
    next(it)
    t0 = time.perf_counter()
    n = 0
    for _ in range(batches):
        n += next(it)["index"].shape[0]
    return n / (time.perf_counter() - t0)


def split_ms(ds, samples: int) -> dict:
    """Median per-sample milliseconds of the transform's steps, in this process."""
    tf = ds.gensplat
    times = {"cache_read": [], "render": [], "resize_convert": [], "transform_total": []}
    torch.set_num_threads(1)  # as in a dataloader worker
    raw = [LeRobotDataset.__getitem__(ds, i) for i in range(samples)]
    for item in raw:
        ep, fr = int(item["episode_index"]), int(item["frame_index"])
        t0 = time.perf_counter()
        rec = tf.cache.read(ep, fr)
        t1 = time.perf_counter()
        for i, name in enumerate(tf.cfg.replace):
            p = tf.sampler.sample(ep, fr)
            cams = rec.cameras
            target = cams[i].with_c2w(p.apply(cams.c2w[i : i + 1], pivot_point(cams.c2w[0], cams.c2w[1])))
            out = render(rec.gaussians, target, backend=tf.cfg.backend, return_depth=False, **tf.cfg.render_options)
        t2 = time.perf_counter()
        (out.rgb.clamp(0, 1) * 255 + 0.5).to(torch.uint8)
        t3 = time.perf_counter()
        tf(item)
        t4 = time.perf_counter()
        for k, v in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3)):
            times[k].append(v * 1e3)
    return {k: round(statistics.median(v), 2) for k, v in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small dataset, few batches (< 1 min)")
    parser.add_argument("--backend", default="fast")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()
    size, episodes, frames, batches = (96, 1, 8, 3) if args.quick else (224, 2, 20, 10)
    root = Path(tempfile.mkdtemp()) / "ds"
    record_scene_dataset(root, SceneEpisodes(episodes, frames, size), REPO, progress=False)
    config = GenSplatConfig(probability=1.0, level="train", backend=args.backend)
    stats = prepare(root, REPO, config, progress=False)
    bytes_per_timestep = sum(s.bytes for s in stats.values()) / sum(s.num_frames for s in stats.values())

    plain = LeRobotDataset(REPO, root=root)
    gensplat = enable_gensplat(LeRobotDataset(REPO, root=root))
    split = split_ms(gensplat, samples=min(8, episodes * frames))
    rate_plain = loader_rate(plain, args.workers, 4, batches)
    rate_gs = loader_rate(gensplat, args.workers, 4, batches)
    result = {
        "quick": args.quick, "backend": args.backend, "workers": args.workers, "resolution": [size, size],
        "cameras_reconstructed": list(config.cameras), "cameras_replaced": list(config.replace),
        "samples_per_s_plain": round(rate_plain, 2), "samples_per_s_gensplat": round(rate_gs, 2),
        "transform_ms": split["transform_total"], "split_ms": split,
        "cache_bytes_per_timestep": round(bytes_per_timestep),
    }  # fmt: skip
    print(f"{'':28}{'value':>12}")
    for k in ("samples_per_s_plain", "samples_per_s_gensplat", "transform_ms", "cache_bytes_per_timestep"):
        print(f"{k:28}{result[k]:>12}")
    for k, v in split.items():
        print(f"  {k:26}{v:>12} ms")
    out = Path(__file__).parent / "results" / "dataloader.json"
    out.parent.mkdir(exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print("wrote", out)


if __name__ == "__main__":
    main()
