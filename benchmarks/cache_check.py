"""What checking a cache before training costs per episode: every header read, against the
index of files found valid before (``SceneCache.statuses``).

    python benchmarks/cache_check.py [--quick] [--episodes 2000] [--frames 100] [--repeats 3] [--out FILE]

Builds a depth cache (stored depth, one tensor per frame, as a model reconstructor's or
``--copy-depth`` cache) of ``--episodes`` episodes of ``--frames`` frames each (the views of
one procedural 16x16 episode reused for all of them: the header's size follows the frame
count, not the pixels), then times, each in a new ``SceneCache`` object:

* ``headers``: ``status`` of every episode (reads and checks every file header; what the
  check before training did without an index);
* ``first_check``: ``statuses`` without an index (the same reads, plus writing the index);
* ``indexed``: ``statuses`` with the index (one ``stat`` per file).

The check before training also digests the dataset's folders (its content fingerprint,
``gensplat_lerobot.source.files_digest``): with one depth file per episode and camera, a
folder of ``--episodes`` files (64 KiB each; only their first and last 16 KiB are read) is
digested by reading every file, and from the digests memo (one ``stat`` per file).

The files are in the page cache in every round (a first check on a cold disk or a network
filesystem reads the headers from storage, and costs more). Medians of ``--repeats`` rounds;
milliseconds per episode (per file for the digests) and the extrapolation to DROID's 76k
episodes. Writes
benchmarks/results/cache_check.json (or ``--out``). ``--quick`` is a smoke run whose figures mean
little: 4 episodes of 2 frames, one round, written to outputs/benchmarks_quick/cache_check.json.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from gensplat_lerobot.source import files_digest
from machine import cpu_model, default_out, out_help, write_result
from tqdm.auto import tqdm

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.cache.store import INDEX_NAME, SceneCache
from gensplat_transforms.geometry import RGBDReconstructor, Views

DROID_EPISODES = 76_000


class Repeated:
    """Episodes that all show the views of one procedural episode (rendered once)."""

    camera_names = ("left", "right")

    def __init__(self, episodes: int, frames: int, size: int) -> None:
        scene = SceneEpisodes(num_episodes=1, num_frames=frames, size=size)
        self.frames = [scene.views(0, t) for t in range(frames)]
        self.episodes = episodes
        self.fingerprint = f"repeated-{episodes}x{frames}-{size}"

    def num_frames(self, episode: int) -> int:
        return len(self.frames)

    def views(self, episode: int, frame: int) -> Views:
        return self.frames[frame]


def timed_ms(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return (time.perf_counter() - t0) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: 4 episodes of 2 frames, one round")
    parser.add_argument("--episodes", type=int, default=2000, help="episodes cached (default: 2000)")
    parser.add_argument("--frames", type=int, default=100, help="frames per episode (default: 100)")
    parser.add_argument("--repeats", type=int, default=3, help="rounds; medians reported (default: 3)")
    parser.add_argument("--out", type=Path, help=out_help("cache_check.json"))
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.frames, args.repeats = 4, 2, 1
    args.out = args.out or default_out("cache_check.json", args.quick)
    source = Repeated(args.episodes, args.frames, 16)
    root, rec = Path(tempfile.mkdtemp(prefix="cache_check_")), RGBDReconstructor()
    cache = SceneCache(root, rec, source.fingerprint)
    for episode in tqdm(range(args.episodes), desc="building", unit="episode"):
        cache.ensure(episode, source)
    episodes, index = range(args.episodes), root / INDEX_NAME

    def new() -> SceneCache:
        return SceneCache(root, rec, source.fingerprint)

    def first_check() -> None:
        index.unlink(missing_ok=True)
        statuses = new().statuses(episodes)
        assert set(statuses.values()) == {"ok"}

    rounds = {"headers": [], "first_check": [], "indexed": []}
    for _ in range(args.repeats):
        rounds["headers"].append(timed_ms(lambda: [new().status(e) for e in episodes]))
        rounds["first_check"].append(timed_ms(first_check))
        rounds["indexed"].append(timed_ms(lambda: new().statuses(episodes)))
    folder = root / "dataset" / "depth" / "left"
    folder.mkdir(parents=True)
    for episode in range(args.episodes):
        (folder / f"episode_{episode:06d}.safetensors").write_bytes(os.urandom(1 << 16))
    memo = root / "dataset" / "digests.json"
    files_digest(root / "dataset", "depth/left", memo)  # writes the memo
    rounds.update(digest_read=[], digest_memo=[])
    for _ in range(args.repeats):
        rounds["digest_read"].append(timed_ms(lambda: files_digest(root / "dataset", "depth/left")))
        rounds["digest_memo"].append(timed_ms(lambda: files_digest(root / "dataset", "depth/left", memo)))
    ms = {k: statistics.median(v) / args.episodes for k, v in rounds.items()}
    result = {
        "quick": args.quick, "episodes": args.episodes, "frames_per_episode": args.frames,
        "episode_file_bytes": cache.path(0).stat().st_size, "index_bytes_per_episode": round(index.stat().st_size / args.episodes, 1),
        "ms_per_episode": {k: round(v, 4) for k, v in ms.items()},
        "indexed_speedup": round(ms["headers"] / ms["indexed"], 1),
        "digest_memo_speedup": round(ms["digest_read"] / ms["digest_memo"], 1),
        "droid_seconds": {k: round(v * DROID_EPISODES / 1e3, 1) for k, v in ms.items()},
        "rounds_ms": rounds, "machine": {"cpus": os.cpu_count(), **cpu_model()}, "load_average": os.getloadavg(),
    }  # fmt: skip
    print(f"{'check':>12} {'ms per episode':>15} {'s at 76k episodes':>18}")
    for k, v in ms.items():
        print(f"{k:>12} {v:>15.4f} {result['droid_seconds'][k]:>18.1f}")
    write_result(result, args.out)


if __name__ == "__main__":
    main()
