"""What a training worker pays to read one timestep's depth from a stored-depth cache.

    python benchmarks/cache_read.py [--quick] [--episodes 8] [--frames 300] [--reads 400] [--cache DIR]
        [--out FILE]

A stored-depth cache (what a model reconstructor or ``--copy-depth`` writes for an RGB-only
or a network-stored dataset) of ``--episodes`` episodes of ``--frames`` frames, two 640x480
views: synthetic depth (a tilted table and a far wall, a box that moves a few pixels a
frame, and 0.05 % per-pixel noise, about one code of the depth codec; the blob size it gives
is reported, and decoding time follows it). Random (episode, frame) reads, one thread,
thread CPU time per read, medians of ``--repeats`` rounds:

* ``warm``: every episode kept parsed (the dataset fits ``keep_bytes``: its headers, cameras
  and decoded depth references stay in memory);
* ``cold``: nothing kept (``keep_bytes=1``), so every read parses the file and decodes its
  reference first: what random access over a dataset far larger than the budget costs
  (DROID: 76k episodes).

Each as ``read_depth_words`` (the int16 words batch-mode workers ship) and ``read_depth``
(float32 metres, what the worker path builds Gaussians from). ``--cache DIR`` builds into
DIR, or reuses the cache there. Writes benchmarks/results/cache_read.json (or ``--out``).
``--quick`` is a smoke run whose figures mean little: 2 episodes of 3 frames, 10 reads, one round,
written to outputs/benchmarks_quick/cache_read.json.
"""

from __future__ import annotations

import argparse
import os
import random
import statistics
import tempfile
import time
from pathlib import Path

import torch
from machine import cpu_model, default_out, out_help, write_result
from tqdm.auto import tqdm

from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.data.scenes import default_cameras
from gensplat_transforms.geometry import RGBDReconstructor, Views

WIDTH, HEIGHT = 640, 480


class SyntheticDepth:
    """Two 640x480 views of a table, a wall and a moving box, with per-pixel noise."""

    def __init__(self, episodes: int, frames: int) -> None:
        self.episodes, self.frames = episodes, frames
        self.cameras = default_cameras(WIDTH, HEIGHT)[:2]
        self.fingerprint = f"synthetic-depth-{episodes}x{frames}"
        y, x = torch.meshgrid(torch.linspace(0, 1, HEIGHT), torch.linspace(0, 1, WIDTH), indexing="ij")
        self.scene = torch.where(y < 0.35, torch.full_like(y, 2.5), 0.7 + 0.8 * y + 0.1 * x)  # wall, table

    def num_frames(self, episode: int) -> int:
        return self.frames

    def views(self, episode: int, frame: int) -> Views:
        g = torch.Generator().manual_seed(episode * 100_003 + frame)
        depth = self.scene.expand(2, 1, HEIGHT, WIDTH).clone()
        x0 = 100 + (3 * frame + 37 * episode) % 400
        depth[:, :, 260:340, x0 : x0 + 90] -= 0.15  # the box
        depth *= 1 + 5e-4 * torch.randn(depth.shape, generator=g)
        return Views(torch.zeros(2, 3, HEIGHT, WIDTH), self.cameras, depth)


def per_read_ms(read, picks) -> float:
    """Thread CPU milliseconds per ``read(episode, frame)`` over ``picks``."""
    t0 = time.thread_time()
    for episode, frame in picks:
        read(episode, frame)
    return (time.thread_time() - t0) / len(picks) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: 2 episodes of 3 frames, 10 reads")
    parser.add_argument("--episodes", type=int, default=8, help="episodes cached (default: 8)")
    parser.add_argument("--frames", type=int, default=300, help="frames per episode (default: 300)")
    parser.add_argument("--reads", type=int, default=400, help="random reads per round (default: 400)")
    parser.add_argument("--repeats", type=int, default=3, help="rounds; medians reported (default: 3)")
    parser.add_argument("--cache", type=Path, help="build the cache here, or reuse it (default: a temporary folder)")
    parser.add_argument("--out", type=Path, help=out_help("cache_read.json"))
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.frames, args.reads, args.repeats = 2, 3, 10, 1
    args.out = args.out or default_out("cache_read.json", args.quick)
    torch.set_num_threads(1)
    source, rec = SyntheticDepth(args.episodes, args.frames), RGBDReconstructor()
    root = args.cache or Path(tempfile.mkdtemp(prefix="cache_read_"))
    cache = SceneCache(root, rec, source.fingerprint, link_depth=False)
    for episode in tqdm(range(args.episodes), desc="building", unit="episode"):
        cache.ensure(episode, source)
    rng = random.Random(0)
    rounds = {f"{mode}_{what}": [] for mode in ("warm", "cold") for what in ("words", "depth")}
    for _ in range(args.repeats):
        for mode, keep in (("warm", 1 << 30), ("cold", 1)):
            reader = SceneCache(root, rec, source.fingerprint, keep_bytes=keep, link_depth=False)
            for episode in range(args.episodes):
                reader.read_depth_words(episode, 0)  # parsed (and kept, when warm) before timing
            picks = [(rng.randrange(args.episodes), rng.randrange(args.frames)) for _ in range(args.reads)]
            if mode == "cold":  # never the same episode twice in a row: a kept file would be reused
                picks = [(i % args.episodes, frame) for i, (_, frame) in enumerate(picks)]
            rounds[f"{mode}_words"].append(per_read_ms(reader.read_depth_words, picks))
            rounds[f"{mode}_depth"].append(per_read_ms(reader.read_depth, picks))
    ms = {k: round(statistics.median(v), 3) for k, v in rounds.items()}
    sizes = [cache.path(e).stat().st_size for e in range(args.episodes)]
    result = {
        "quick": args.quick, "episodes": args.episodes, "frames_per_episode": args.frames, "views": 2,
        "size": [WIDTH, HEIGHT],
        "bytes_per_frame": round(sum(sizes) / (args.episodes * args.frames)), "reads_per_round": args.reads,
        "ms_per_read": ms, "rounds_ms": rounds, "torch_threads": torch.get_num_threads(),
        "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg(),
    }  # fmt: skip
    print(f"{result['bytes_per_frame']:,} bytes per frame (2 views of {WIDTH}x{HEIGHT})")
    print(f"{'read':>12} {'warm ms':>9} {'cold ms':>9}")
    for what in ("words", "depth"):
        print(f"{what:>12} {ms[f'warm_{what}']:>9.3f} {ms[f'cold_{what}']:>9.3f}")
    write_result(result, args.out)


if __name__ == "__main__":
    main()
