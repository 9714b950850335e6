"""Cache build throughput of ``gensplat cache`` with 1 and 2 processes on one machine.

    python benchmarks/cache_build.py [--quick] [--episodes 6] [--size 224] [--processes 1 2] [--repeats 3]
        [--root DIR] [--out FILE]

Records a simulated pick-and-place dataset once (MP4 video like LeRobot's default, depth
sidecars of the two external cameras; reused when ``--root`` already holds it), then builds
its cache from scratch (RGB-D reconstructor) with each process count: a plain ``gensplat
cache`` for 1, ``torchrun --standalone --nproc-per-node N`` for N > 1, one thread per
process (what torchrun sets), in two modes: ``link`` (the default: the cache links the depth
sidecars, so a build checks and checksums them) and ``copy`` (``--copy-depth``: every item is
loaded, its depth cleaned, compressed and stored, as a model reconstructor's build stores its
predicted depth). ``--repeats`` rounds alternate the counts and the fastest
build of each is reported (the machine may be shared). Reported: the build's episodes and
timesteps per second (the time ``gensplat cache`` prints: from the start of ``prepare`` to
the last process's end), timesteps per CPU second of the build (all processes' CPU time:
what a core-hour estimate needs, and less sensitive to other jobs than the wall time), end
to end (the whole command, with interpreter start and imports), and cache bytes per
timestep. For a plan at DROID's size, each reconstructor (rgbd, geometry and gensplat, the
models being the shipped small one) also builds a few timesteps of the procedural scene
seen by two 320x180 cameras, in this process with one thread: cache bytes and CPU seconds
per timestep, and a depth build's peak memory against its episode's length (two 640x480
cameras, 50 and 200 frames, each in a fresh process). Writes benchmarks/results/cache_build.json
(or ``--out``). ``--quick`` is a smoke run whose figures mean little: 2 episodes at 32x32 (in
outputs/benchmarks_quick/cache_build_ds unless ``--root``), one build linking the depth with one
process and one copying it with two, one DROID-size timestep, episodes of 2 and 4 frames for the
memory, written to outputs/benchmarks_quick/cache_build.json.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.world import WorldConfig
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.data.scenes import default_cameras
from gensplat_transforms.geometry import (
    GenSplatReconstructor,
    GeometryReconstructor,
    RGBDReconstructor,
    Views,
)

REPO = "gensplat/bench_cache_build"


def build(root: Path, processes: int, mode: str) -> dict:
    """Build the cache of ``root`` from scratch with ``processes`` processes, linking or copying
    the depth (``mode``); times and sizes."""
    shutil.rmtree(root / "gensplat", ignore_errors=True)
    torchrun = ["-m", "torch.distributed.run", "--standalone", "--nproc-per-node", str(processes)]
    cli = ["-m", "gensplat_cli", "cache", "--root", str(root), "--repo-id", REPO,
           *(["--copy-depth"] if mode == "copy" else [])]  # fmt: skip
    cmd = [sys.executable, *(torchrun if processes > 1 else []), *cli]
    t0 = time.perf_counter()
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    run = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    line = next(x for x in run.stdout.splitlines() if x.startswith("cached "))
    seconds, cpu = (float(x) for x in re.search(r" in ([\d.]+) s, ([\d.]+) CPU s ", line).groups())
    info = json.loads((root / "meta" / "info.json").read_text())
    episodes, timesteps = info["total_episodes"], info["total_frames"]
    size = sum(f.stat().st_size for f in (root / "gensplat" / "cache").rglob("episode_*.safetensors"))
    return {"mode": mode, "processes": processes, "build_s": seconds, "episodes_per_s": round(episodes / seconds, 3),
            "timesteps_per_s": round(timesteps / seconds, 2), "build_cpu_s": cpu,
            "timesteps_per_cpu_s": round(timesteps / cpu, 2), "end_to_end_s": round(wall, 1),
            "end_to_end_episodes_per_s": round(episodes / wall, 3), "cache_bytes": size,
            "bytes_per_timestep": round(size / timesteps), "summary": line}  # fmt: skip


class Rendered:
    """The views of :class:`SceneEpisodes` episode 0 (one object sliding across the table) seen by
    two ``width`` x ``height`` cameras, rendered once up front."""

    camera_names = ("left", "right")

    def __init__(self, width: int, height: int, frames: int) -> None:
        scene = SceneEpisodes(num_episodes=1, num_frames=frames)
        scene.cameras = default_cameras(width, height)
        self.frames = [scene.views(0, t) for t in range(frames)]
        self.fingerprint = f"scene-{width}x{height}-{frames}"

    def num_frames(self, episode: int) -> int:
        return len(self.frames)

    def views(self, episode: int, frame: int) -> Views:
        return self.frames[frame]


def droid_size(frames: int) -> dict:
    """Cache bytes and CPU seconds per timestep of each reconstructor at 320x180 (this process,
    one thread)."""
    torch.set_num_threads(1)
    source, out = Rendered(320, 180, frames), {}
    for rec in (RGBDReconstructor(), GeometryReconstructor(), GenSplatReconstructor()):
        cache = SceneCache(tempfile.mkdtemp(), rec, source.fingerprint)
        t0 = time.perf_counter()
        stats = cache.ensure(0, source)
        out[rec.name] = {"bytes_per_timestep": round(stats.bytes_per_timestep),
                         "cpu_s_per_timestep": round((time.perf_counter() - t0) / frames, 3)}  # fmt: skip
    return {"resolution": [320, 180], "timesteps": frames, "threads": 1, **out}


class Streamed:
    """An episode of ``frames`` views of two 640x480 cameras made as they are asked for (random
    colours, a smooth depth ramp that changes each frame), as a long recording's decoder
    gives them."""

    camera_names = ("left", "right")
    fingerprint = "streamed-640x480"

    def __init__(self, frames: int) -> None:
        self.frames, self.cameras = frames, default_cameras(640, 480)[:2]

    def num_frames(self, episode: int) -> int:
        return self.frames

    def views(self, episode: int, frame: int) -> Views:
        depth = (1.0 + 0.001 * frame + 0.3 * torch.linspace(0, 1, 640)).expand(2, 1, 480, 640).contiguous()
        return Views(torch.rand(2, 3, 480, 640), self.cameras, depth)


def resident_mb() -> float:
    """This process's resident memory now (Linux)."""
    return int(Path("/proc/self/statm").read_text().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def episode_memory(frames: int) -> float:
    """Peak resident memory growth (MB) of this process while it builds a depth cache (stored
    copy) of a :class:`Streamed` episode of ``frames`` frames, sampled every 2 ms against the
    resident memory before (the peak of the imports before does not hide it)."""
    source = Streamed(frames)
    cache = SceneCache(tempfile.mkdtemp(), RGBDReconstructor(), source.fingerprint, link_depth=False)
    source.views(0, 0)
    before, peak, done = resident_mb(), [0.0], threading.Event()

    def sample():
        while not done.wait(0.002):
            peak[0] = max(peak[0], resident_mb())

    sampler = threading.Thread(target=sample)
    sampler.start()
    try:
        cache.ensure(0, source)
    finally:
        done.set()
        sampler.join()
    return max(peak[0], resident_mb()) - before


def build_memory(counts: tuple[int, ...] = (50, 200)) -> dict:
    """A depth build's peak memory against the episode's length, each in a fresh process: MB
    per frame from the difference (what a long episode adds), at 640x480, two cameras."""
    peak = {}
    for n in counts:
        run = subprocess.run([sys.executable, __file__, "--episode-memory", str(n)], check=True, capture_output=True,
                             text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})  # fmt: skip
        peak[n] = float(run.stdout.split()[-1])
    per_frame = (peak[counts[-1]] - peak[counts[0]]) / (counts[-1] - counts[0])
    return {"resolution": [640, 480], "cameras": 2, "peak_resident_growth_mb": peak, "mb_per_frame": round(per_frame, 2)}


def main() -> None:
    if sys.argv[1:2] == ["--episode-memory"]:  # the child process of build_memory
        print(round(episode_memory(int(sys.argv[2])), 1))
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a smoke run: tiny dataset, one round (seconds)")
    parser.add_argument("--episodes", type=int, default=6, help="episodes to record, if not reused (default: 6)")
    parser.add_argument("--size", type=int, default=224, help="image size to record, if not reused (default: 224)")
    parser.add_argument("--processes", type=int, nargs="+", default=[1, 2],
                        help="process counts (default: 1 2)")
    parser.add_argument("--modes", nargs="+", choices=["link", "copy"], default=["link", "copy"],
                        help="depth linked (the default cache) and/or copied (--copy-depth) (default: both)")
    parser.add_argument("--repeats", type=int, default=3,
                        help="builds per process count; the fastest is reported (default: 3)")
    parser.add_argument("--droid-frames", type=int, default=8,
                        help="timesteps built at DROID's size per reconstructor (default: 8)")
    parser.add_argument("--root", help="the dataset, recorded if absent (default: outputs/benchmarks/"
                        "cache_build_ds; with --quick outputs/benchmarks_quick/cache_build_ds)")
    parser.add_argument("--out", type=Path, help=out_help("cache_build.json"))
    args = parser.parse_args()
    memory_frames = (50, 200)
    if args.quick:
        args.episodes, args.size, args.repeats, args.droid_frames, memory_frames = 2, 32, 1, 1, (2, 4)
    default_root = default_out("cache_build_ds", True) if args.quick else "outputs/benchmarks/cache_build_ds"
    root = Path(args.root or default_root)
    if not (root / "meta" / "info.json").exists():
        record(RecordConfig(root, "pick_place", args.episodes, seed=0, repo_id=REPO,
                            world=WorldConfig(width=args.size, height=args.size)), progress=False)  # fmt: skip
    info = json.loads((root / "meta" / "info.json").read_text())
    runs = []
    settings = [(m, n) for m in args.modes for n in args.processes]
    if args.quick:  # each mode once, each process count once
        settings = [("link", 1), ("copy", 2)]
    for _ in range(args.repeats):  # alternated, so a busy spell of a shared machine hits every setting
        for mode, n in settings:
            load = os.getloadavg()[0]
            runs.append({**build(root, n, mode), "load_average_before": round(load, 2)})
    best = [min((r for r in runs if (r["mode"], r["processes"]) == s), key=lambda r: r["build_s"])
            for s in settings]  # fmt: skip
    result = {
        "dataset": {"episodes": info["total_episodes"], "timesteps": info["total_frames"],
                    "resolution": info["features"]["observation.images.left"]["shape"][:2], "reconstructed_cameras": 2, "video": True},
        "reconstructor": "rgbd", "best": best, "runs": runs, "droid_size": droid_size(args.droid_frames),
        "build_memory": build_memory(memory_frames), "quick": args.quick,
        "machine": {"cpus": os.cpu_count(), **cpu_model()}, "gpu": None,
    }  # fmt: skip
    print(f"best of {args.repeats} runs (fastest build)")
    print(f"{'mode':>5}{'processes':>10}{'episodes/s':>12}{'timesteps/s':>13}{'build s':>9}{'CPU s':>8}"
          f"{'timesteps/CPU s':>17}{'end-to-end s':>14}{'B/timestep':>12}")
    for r in best:
        print(f"{r['mode']:>5}{r['processes']:>10}{r['episodes_per_s']:>12}{r['timesteps_per_s']:>13}{r['build_s']:>9}"
              f"{r['build_cpu_s']:>8}{r['timesteps_per_cpu_s']:>17}{r['end_to_end_s']:>14}"
              f"{r['bytes_per_timestep']:>12}")
    print("at 320x180:", json.dumps(result["droid_size"]))
    print("a depth build's peak memory:", json.dumps(result["build_memory"]))
    write_result(result, args.out or default_out("cache_build.json", args.quick))


if __name__ == "__main__":
    main()
