"""Where a Diffusion Policy training step's time goes in the policy study: loading an item, and
LeRobot's own step log (``updt_s``: forward, backward and optimiser step; ``data_s``: waiting
for the batch), with LeRobot 0.6.1 as it is and with ``gensplat_lerobot.fast_rows``.

    python benchmarks/training_step.py [--root DATASET] [--steps 30] [--quick] [--out FILE]

Without ``--root`` it records ``--demos`` demonstrations of the study's task first. Writes
``benchmarks/results/training_step.json``; ``--quick`` (under a minute: two demonstrations at
48 px, 4 steps of one setting, figures that mean nothing) writes
``outputs/training_step_quick.json`` instead (``--out``: elsewhere).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

os.environ.setdefault("HF_HUB_OFFLINE", "1")

import policy_robustness as pr
from machine import cpu_model

from gensplat_transforms.core.atomic import atomic_write_json

#: (label, dataloader workers, with fast_rows)
SETTINGS = (("as it is, 2 workers", 2, False), ("as it is, no workers", 0, False),
            ("fast_rows, no workers", 0, True), ("fast_rows, 2 forked workers", 2, True))  # fmt: skip


def item_ms(root: Path, repo_id: str, items: int) -> float:
    """Mean milliseconds to load one item with the study's queries (16 actions, one observation)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    query = {"action": [i / 10 for i in range(16)]}
    ds = LeRobotDataset(repo_id, root=root, delta_timestamps=query)
    order = np.random.default_rng(0).permutation(len(ds))[:items]
    ds[int(order[0])]
    t0 = time.perf_counter()
    for i in order:
        ds[int(i)]
    return 1000 * (time.perf_counter() - t0) / len(order)


def step_log(root: Path, work: Path, workers: int, fast_rows: bool, args) -> dict:
    """Median ``updt_s`` and ``data_s`` of a short baseline training (the first log line left out)."""
    run_args = pr.parse_args(["--size", str(args.size), "--steps", str(args.steps), "--workers", str(workers),
                              "--arms", "baseline", "--work", str(work)] + (["--quick"] if args.quick else []))  # fmt: skip
    out = work / f"run_{workers}_{int(fast_rows)}"
    shutil.rmtree(out, ignore_errors=True)
    cmd = pr.train_command("baseline", root, out, pr.policy_config(work, run_args), run_args)
    cmd = [c for c in cmd if fast_rows or not c.startswith(("--fast_rows.", "--dataloader_multi"))]
    if not fast_rows and workers:
        cmd.append("--dataloader_multiprocessing_context=spawn")  # LeRobot's default
    cmd.append(f"--log_freq={max(1, args.steps // 6)}")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, check=False)
    text = run.stdout + run.stderr
    if run.returncode != 0:
        raise RuntimeError(f"training failed (exit {run.returncode}):\n{text[-2000:]}")
    updt, data = ([float(x) for x in re.findall(rf"{k}:([0-9.]+)", text)][1:] for k in ("updt_s", "data_s"))
    return {"updt_s": float(np.median(updt)) if updt else None, "data_s": float(np.median(data)) if data else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", type=Path, help="a recorded dataset of the study (default: record one)")
    parser.add_argument("--task", default="reach_solo")
    parser.add_argument("--demos", type=int, default=30)
    parser.add_argument("--size", type=int, default=96)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--items", type=int, default=200)
    parser.add_argument("--quick", action="store_true", help="seconds-long check: 2 demos at 48 px, 4 steps")
    parser.add_argument("--out", type=Path, help="result file (default: benchmarks/results/training_step.json; "
                        "with --quick outputs/training_step_quick.json)")
    args = parser.parse_args()
    if args.quick:
        args.demos, args.size, args.steps, args.items = 2, 48, 4, 5
    work = pr.ROOT / "outputs" / ("training_step_quick" if args.quick else "training_step")
    root = args.root or work / "dataset"
    if not (root / "meta" / "info.json").is_file():
        shutil.rmtree(root, ignore_errors=True)
        pr.record(pr.RecordConfig(root, args.task, args.demos, 0, use_videos=False, repo_id=pr.repo_id(args.task),
                                  world=pr.WorldConfig(height=args.size, width=args.size)), progress=False)  # fmt: skip
    from gensplat_lerobot import fast_rows
    from lerobot.datasets.dataset_reader import DatasetReader

    DatasetReader._query_hf_dataset = fast_rows._ORIGINAL
    items = {False: item_ms(root, pr.repo_id(args.task), args.items)}
    fast_rows.install()
    items[True] = item_ms(root, pr.repo_id(args.task), args.items)
    rows = []
    print(f"{'setting':>28} {'item ms':>8} {'updt_s':>7} {'data_s':>7} {'s/step':>7}")
    for label, workers, fast in SETTINGS[2:3] if args.quick else SETTINGS:
        log = step_log(root, work, workers, fast, args)
        step = None if None in log.values() else round(log["updt_s"] + log["data_s"], 3)
        rows.append({"setting": label, "workers": workers, "fast_rows": fast, "item_ms": round(items[fast], 2), **log,
                     "s_per_step": step})  # fmt: skip
        print(f"{label:>28} {items[fast]:8.1f} {log['updt_s'] or 0:7.3f} {log['data_s'] or 0:7.3f} {step or 0:7.3f}")
    out = args.out or (work.parent / "training_step_quick.json" if args.quick else pr.RESULTS / "training_step.json")
    atomic_write_json(out, {"machine": cpu_model(), "size": args.size, "batch_size": 4 if args.quick else 32,
                            "steps": args.steps, "quick": args.quick, "rows": rows})  # fmt: skip
    print("wrote", out)


if __name__ == "__main__":
    main()
