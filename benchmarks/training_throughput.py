"""Training throughput of Diffusion Policy in lerobot-train: plain, GenSplat rendering in the
dataloader workers, and GenSplat rendering each batch on the training GPU.

    python benchmarks/training_throughput.py [--quick] [--batch-size B] [--workers W] [--steps N]
        [--size S] [--episodes E] [--probability P] [--repeats R] [--modes plain,worker,batch]
        [--config policies/diffusion.json]
        [--root DIR] [--out results/training_throughput.json]

A simulated pick-and-place dataset (two external cameras with depth and a wrist camera, S x S,
MP4 video as users' datasets are) is recorded and its GenSplat cache built (``--root``: kept in
DIR and reused when it holds a recording, e.g. one made on another machine). Then the stock
``lerobot-train`` trains the same policy config (``--config``; default the small CPU Diffusion
Policy) with the same batch size, workers and seed three times: without GenSplat ("plain"), with
GenSplat at ``--probability`` rendering in the workers ("worker", the fast CPU backend), and
rendering each batch after collation on the GPU ("batch", gsplat; needs CUDA: without it the row
is recorded as missing). Samples per second over the last ``N`` steps (after ``N`` warm-up
steps) are lerobot-train's own ``batch / (updt_s + data_s)``, its averages over that log window;
on CUDA, ``gpu_busy`` is the mean GPU utilisation (NVML, sampled every 0.5 s) in that window.
The modes run in turn, ``R`` rounds; each row is its best run (all runs are recorded), so that a
load that other jobs put on the machine for a while does not pass for a mode's cost. An epoch
must hold at least two batches per worker: LeRobot's loader gives each batch of an epoch to one
worker and begins the next epoch after the last batch, so with fewer batches the workers wait on
the epoch's end (6 persistent workers fed 31 % of their rate from 2 batches per epoch, 93 % from
12, 96-98 % from 24). The default ``E`` records four batches per worker. A recording of PNG
images (``--root``) is slow to load in LeRobot: each query of a delta timestamp decodes every
image column of every row it reads (75 decodes per Diffusion Policy sample for the 6 frames it
uses), so the loader, not the GPU, sets the pace; the result records ``storage``. The result is
rewritten after each run (``complete``: false until the last), so a run cut short keeps its
rows. Defaults: batch 64, 6 workers, 224x224, 50 steps on CUDA (26 episodes); batch 8, 2
workers, 96x96, 5 steps on a CPU (3 episodes). ``--config policies/diffusion_full.json`` is
LeRobot's Diffusion Policy at its default widths (no pretrained backbone: nothing is
downloaded). Before the runs, ``loader`` measures what each mode costs a dataloader worker
per sample (``--loader-rounds`` rounds over the same batches, one thread, no GPU needed):
while training waits on its loader, samples/s scale as its inverse.
Writes benchmarks/results/training_throughput.json (or --out). ``--quick`` is a smoke run whose
figures mean little (batch 4, one worker, 64x64, one episode, one warm-up and one measured step,
one round of each; written to outputs/benchmarks_quick/training_throughput.json).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import Self

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import torch
from gensplat_lerobot import enable_gensplat, load_settings, prepare, save_settings
from machine import cpu_model, default_out, out_help, write_result

from gensplat_transforms.transform import GenSplatConfig

REPO = "gensplat/bench_pick_place"
HERE = Path(__file__).resolve().parent
TRAIN_SH = HERE.parent / "policies" / "train.sh"
#: lerobot-train's log line: "INFO 2026-11-26 16:36:56 ot_train.py:641 step:20 ... updt_s:0.123 data_s:0.010 ..."
LOG_LINE = re.compile(r"(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d) \S+ step:(\S+) .*updt_s:([\d.]+) data_s:([\d.]+)")
#: an epoch must give each dataloader worker this many batches (see main)
MIN_BATCHES_PER_WORKER = 2
#: frames of one simulated pick-and-place episode, about
EPISODE_FRAMES = 60
#: the GenSplat plugin's line at the same steps
AUGMENTED = re.compile(r"GenSplat step \d+: (\d+) of (\d+) samples augmented")


class GpuBusy:
    """GPU utilisation (%, NVML through torch) sampled every ``period`` s in a thread while the
    context is open; ``mean(start, end)`` over a window of Unix times (None without samples)."""

    def __init__(self, period: float = 0.5):
        self.samples: list[tuple[float, float]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._sample, args=(period,), daemon=True)

    def _sample(self, period: float) -> None:
        while not self._stop.wait(period):
            try:
                self.samples.append((time.time(), float(torch.cuda.utilization())))
            except Exception as error:  # noqa: BLE001 (pynvml missing, or NVML's own error types)
                print(f"GPU utilisation not sampled: {error}", file=sys.stderr)
                return

    def __enter__(self) -> Self:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def mean(self, start: float, end: float) -> float | None:
        window = [busy for t, busy in self.samples if start <= t <= end]
        return round(sum(window) / len(window), 1) if window else None


def log_time(stamp: str) -> float:
    """Unix time of a lerobot-train log stamp ("2026-11-26 16:36:56", this machine's local time)."""
    return datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S").timestamp()


def train(root: Path, config: Path, mode: str, args, device: str) -> dict:
    """One lerobot-train run: samples/s and the step split over its last log window. Its log
    is written as it runs (the path is printed first), so a run cut short leaves its trace."""
    out = Path(tempfile.mkdtemp(prefix=f"throughput_{mode}_"))
    overrides = [
        f"--dataset.repo_id={REPO}", f"--dataset.root={root}",
        f"--output_dir={out / 'out'}", f"--policy.device={device}",
        f"--batch_size={args.batch_size}", f"--num_workers={args.workers}", f"--steps={2 * args.steps}",
        f"--log_freq={args.steps}", "--save_checkpoint=false", "--seed=0",
    ]  # fmt: skip
    cmd = ["bash", str(TRAIN_SH), str(config), "baseline" if mode == "plain" else "gensplat", *overrides]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    print(f"{mode}: lerobot-train, log {out / 'train.log'}", flush=True)
    t0, load = time.perf_counter(), os.getloadavg()[0]
    busy = GpuBusy() if device == "cuda" else contextlib.nullcontext()
    with open(out / "train.log", "w") as log_file, busy:
        run = subprocess.run(cmd, stdout=log_file, stderr=subprocess.STDOUT, text=True, env=env, check=False)
    log = (out / "train.log").read_text()
    if run.returncode != 0:
        raise RuntimeError(f"lerobot-train ({mode}) failed:\n{log[-3000:]}")
    lines = LOG_LINE.findall(log)
    end, step, update_s, data_s = lines[-1]
    update_s, data_s = float(update_s), float(data_s)
    row = {"samples_per_s": round(args.batch_size / (update_s + data_s), 2), "update_s": update_s,
           "data_s": data_s, "window_steps": args.steps, "last_step": step,
           "run_s": round(time.perf_counter() - t0, 1), "load_average_at_start": round(load, 2)}  # fmt: skip
    if device == "cuda" and len(lines) > 1:
        row["gpu_busy"] = busy.mean(log_time(lines[-2][0]), log_time(end))
    print(f"{mode}: {row['samples_per_s']} samples/s ({row['run_s']} s)", flush=True)
    if mode != "plain":
        augmented, samples = map(int, AUGMENTED.findall(log)[-1])
        row["augmented_share"] = round(augmented / max(samples, 1), 3)
    return row


def loader_cost(root: Path, policy_config: Path, config: GenSplatConfig, reconstructor: dict, modes: list[str],
                batch_size: int, batches: int, rounds: int) -> dict:
    """Wall milliseconds per sample that a dataloader worker spends on each mode's items
    (``LeRobotDataset[i]`` with the policy's delta timestamps, GenSplat's transform where
    enabled, then collation into batches of ``batch_size``), on one thread as in a worker.
    The modes take turns over the same ``batches`` random batches with the same draws, for
    ``rounds`` rounds; each mode's figure is its median round, and its rate against plain's
    the median of the rounds' ratios (a round's modes run back to back, so a load that comes
    and goes shifts them alike). When training waits on its loader, samples/s scale as
    1 / these figures."""
    from lerobot.datasets.dataset_metadata import LeRobotDatasetMetadata
    from lerobot.datasets.factory import resolve_delta_timestamps
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy_config
    from torch.utils.data import default_collate

    settings = json.loads(policy_config.read_text())
    policy = {**settings["policy"], "device": "cuda" if torch.cuda.is_available() else "cpu"}
    policy = make_policy_config(policy.pop("type"), **policy)
    deltas = resolve_delta_timestamps(policy, LeRobotDatasetMetadata(REPO, root=root))
    backend = settings.get("dataset", {}).get("video_backend")
    datasets = {}
    for mode in modes:
        ds = LeRobotDataset(REPO, root=root, delta_timestamps=deltas, video_backend=backend)
        datasets[mode] = ds if mode == "plain" else enable_gensplat(ds, replace(config, render_in=mode), reconstructor)
    order = torch.randint(len(ds), (rounds, batches, batch_size), generator=torch.Generator().manual_seed(0))
    threads, times = torch.get_num_threads(), {mode: [] for mode in modes}
    torch.set_num_threads(1)
    try:
        for r in range(rounds):
            for mode, ds in datasets.items():
                torch.manual_seed(r)  # the same samples augmented, with the same moves, in each mode
                t0 = time.perf_counter()
                for batch in order[r]:
                    default_collate([ds[int(i)] for i in batch])
                times[mode].append(round((time.perf_counter() - t0) / order[r].numel() * 1e3, 2))
    finally:
        torch.set_num_threads(threads)
    ratios = {mode: statistics.median(p / m for p, m in zip(times["plain"], t)) for mode, t in times.items()}
    return {"ms_per_sample": {mode: statistics.median(t) for mode, t in times.items()},
            "of_plain": {mode: round(r, 3) for mode, r in ratios.items()},
            "rounds_ms": times, "samples_per_round": order[0].numel()}  # fmt: skip


def main() -> None:
    cuda = torch.cuda.is_available()
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny dataset and few steps (a smoke run)")
    parser.add_argument("--batch-size", type=int, default=64 if cuda else 8)
    parser.add_argument("--workers", type=int, default=6 if cuda else 2)
    parser.add_argument("--steps", type=int, default=50 if cuda else 5, help="warm-up steps, then measured steps")
    parser.add_argument("--size", type=int, default=224 if cuda else 96, help="image height and width")
    parser.add_argument("--episodes", type=int, help=f"recorded episodes (default: {MIN_BATCHES_PER_WORKER * 2} "
                        "batches per worker in an epoch; at least 2)")
    parser.add_argument("--probability", type=float, default=0.5)
    parser.add_argument("--repeats", type=int, default=2, help="rounds of runs; a row is its mode's best run (0: only the loader cost)")
    parser.add_argument("--modes", default="plain,worker,batch", help="modes in the order they run (plain first: "
                        "the others are compared with it); batch needs CUDA")
    parser.add_argument("--loader-rounds", type=int, default=3, help="rounds of the loader-side cost (0: skip it)")
    parser.add_argument("--config", type=Path, default=HERE.parent / "policies" / "diffusion.json")
    parser.add_argument("--root", type=Path, help="dataset folder, reused when it holds a recording (default: temporary)")
    parser.add_argument("--out", type=Path, help=out_help("training_throughput.json"))
    args = parser.parse_args()
    args.out = args.out or default_out("training_throughput.json", args.quick)
    if args.quick:
        args.batch_size, args.workers, args.steps, args.size, args.episodes, args.repeats = 4, 1, 1, 64, 1, 1
        args.loader_rounds = min(args.loader_rounds, 1)
    device = "cuda" if cuda else "cpu"
    args.modes = args.modes.split(",")
    if args.modes[0] != "plain" or not set(args.modes) <= {"plain", "worker", "batch"}:
        parser.error(f"--modes: plain first, then worker and/or batch; got {','.join(args.modes)}")
    if args.episodes is None:
        batches = MIN_BATCHES_PER_WORKER * 2 * args.workers
        args.episodes = max(2, math.ceil(batches * args.batch_size / EPISODE_FRAMES))

    root = args.root or Path(tempfile.mkdtemp()) / "ds"
    info = root / "meta" / "info.json"
    if not info.exists():
        from gensplat_sim.record import RecordConfig, record  # MuJoCo: only to record
        from gensplat_sim.world import WorldConfig

        record(RecordConfig(root, "pick_place", args.episodes, seed=0, use_videos=True, repo_id=REPO,
                            world=WorldConfig(width=args.size, height=args.size)), progress=False)  # fmt: skip
    meta = json.loads(info.read_text())
    left = meta["features"]["observation.images.left"]
    height, width, _ = left["shape"]
    if (height, width) != (args.size, args.size):
        raise SystemExit(f"{root} holds {height}x{width} images, not --size {args.size}")
    batches_per_epoch = meta["total_frames"] // args.batch_size
    if batches_per_epoch < MIN_BATCHES_PER_WORKER * max(args.workers, 1):
        raise SystemExit(
            f"{root} holds {meta['total_frames']} frames: {batches_per_epoch} batches of {args.batch_size} per epoch, "
            f"fewer than {MIN_BATCHES_PER_WORKER} per worker ({args.workers} workers). LeRobot's loader hands each "
            "batch of an epoch to one worker and starts the next epoch after the last, so most workers would "
            "wait and the rows would measure the epoch's end, not the rendering. Record more episodes.")
    prepare(root, REPO, GenSplatConfig(probability=args.probability), progress=False)
    config, reconstructor = load_settings(root)
    if args.loader_rounds > 0:
        loader = loader_cost(root, args.config, config, reconstructor, ["plain", "batch", "worker"], args.batch_size,
                             4, args.loader_rounds)  # fmt: skip
        print(f"{'loader':8}{'ms/sample':>12}{'of plain':>10}")
        for mode, ms in loader["ms_per_sample"].items():
            print(f"{mode:8}{ms:>12}{loader['of_plain'][mode]:>10}")
    load_before = os.getloadavg()
    runs = {mode: [] for mode in args.modes if cuda or mode != "batch"}
    failures = {}
    result = {
        "quick": args.quick, "policy_config": str(args.config.resolve().relative_to(HERE.parent)),
        "device": torch.cuda.get_device_name() if cuda else "cpu", "batch_size": args.batch_size,
        "workers": args.workers, "resolution": [args.size, args.size], "episodes": meta["total_episodes"],
        "storage": left["dtype"], "batches_per_epoch": batches_per_epoch,
        "probability": args.probability, "cameras_replaced": list(config.replace), "repeats": args.repeats,
        "machine": {"cpus": os.cpu_count(), **cpu_model()},
    }  # fmt: skip
    if args.loader_rounds > 0:
        result["loader"] = loader
    for _ in range(args.repeats):
        for mode, done in runs.items():  # plain ignores the settings
            save_settings(root, replace(config, render_in="worker" if mode == "plain" else mode), reconstructor)
            try:
                done.append(train(root, args.config, mode, args, device))
            except RuntimeError as error:  # recorded; the other modes still run
                print(error, file=sys.stderr)
                failures[mode] = str(error)[-1500:]
            result.update(complete=False, rows=rows_of(runs, failures, cuda))
            write_result(result, args.out)  # a run cut short keeps the rows so far
    load = {"before": load_before, "after": os.getloadavg()}
    result.update(complete=True, rows=rows_of(runs, failures, cuda), load_average=load)
    print(f"{'':8}{'samples/s':>12}{'of plain':>10}{'update s':>10}{'data s':>10}{'GPU busy %':>12}")
    for name, row in result["rows"].items():
        if "samples_per_s" not in row:
            print(f"{name:8}  {next(iter(row))}: {next(iter(row.values()))[-200:]}")
        else:
            print(f"{name:8}{row['samples_per_s']:>12}{row.get('of_plain', '-'):>10}{row['update_s']:>10}"
                  f"{row['data_s']:>10}{row.get('gpu_busy', '-')!s:>12}")
    write_result(result, args.out)


def rows_of(runs: dict[str, list[dict]], failures: dict[str, str], cuda: bool) -> dict[str, dict]:
    """Each mode's row: its best run (with every run's samples/s and its share of plain's), its
    failure, or why it is missing."""
    rows = {}
    for mode, done in runs.items():
        if done:
            best = max(done, key=lambda row: row["samples_per_s"])
            rows[mode] = {**best, "samples_per_s_runs": [row["samples_per_s"] for row in done]}
        else:
            rows[mode] = {"failed": failures[mode]} if mode in failures else {"missing": "not run yet"}
    if not cuda:
        rows["batch"] = {"missing": "no CUDA device: GenSplat batched on the GPU renders with gsplat on CUDA"}
    plain = rows["plain"].get("samples_per_s")
    for row in rows.values():
        if "samples_per_s" in row and plain:
            row["of_plain"] = round(row["samples_per_s"] / plain, 3)
    return rows


if __name__ == "__main__":
    main()
