"""Simulated tabletop benchmark: physics, rendering and LeRobot recording speed, and the
scripted experts' success rates.

Rows:
* physics: one 10 Hz control step (IK + 50 MuJoCo steps), expert rollouts without rendering;
* render: the three 224x224 cameras, RGB + metric depth, per timestep;
* record (video / images): end-to-end ``record`` throughput in timesteps per second (expert
  rollout, rendering, LeRobot frame writing, AV1 encoding or PNG, depth and sim sidecars);
* expert success per task over seeded episodes (physics only).

Usage: ``python benchmarks/sim_record.py [--quick] [--out FILE]`` (``--quick``: under a minute, a
smoke run whose figures mean little). Prints a table and writes ``benchmarks/results/sim_record.json``
(``outputs/benchmarks_quick/sim_record.json`` with ``--quick``; or ``--out``).
"""

from __future__ import annotations

import argparse
import platform
import shutil
import tempfile
import time
from pathlib import Path

import torch
from gensplat_sim.experts import run_expert
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.tasks import TASKS, episode_seed
from gensplat_sim.world import CAMERA_NAMES, SimWorld
from machine import default_out, out_help, write_result


def bench_physics_and_render(episodes: int) -> dict:
    world = SimWorld("pick_place")
    steps, start = 0, time.perf_counter()
    states = []
    for i in range(episodes):
        _, ep_states, _, _ = run_expert(world, episode_seed(0, i))
        steps += len(ep_states)
        states += ep_states
    physics = (time.perf_counter() - start) / steps
    world.render()  # warm up
    start = time.perf_counter()
    for s in states[:60]:
        world.set_state(s)
        world.render(CAMERA_NAMES, depth=True)
    render = (time.perf_counter() - start) / min(len(states), 60)
    world.close()
    return {"physics_ms_per_step": 1000 * physics, "render_ms_per_timestep": 1000 * render}


def bench_record(episodes: int, use_videos: bool) -> dict:
    tmp = Path(tempfile.mkdtemp())
    try:
        r = record(
            RecordConfig(tmp / "ds", task="pick_place", episodes=episodes, use_videos=use_videos),
            progress=False,
        )
        size = sum(f.stat().st_size for f in r.root.rglob("*") if f.is_file())
        return {
            "episodes": r.episodes,
            "timesteps": r.frames,
            "seconds": r.seconds,
            "timesteps_per_s": r.frames_per_second,
            "mb_per_episode": size / 1e6 / r.episodes,
        }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def bench_experts(episodes: int) -> dict:
    out = {}
    for task in sorted(TASKS):
        world = SimWorld(task)
        ok = int(sum(run_expert(world, episode_seed(0, i))[3] for i in range(episodes)))
        world.close()
        out[task] = {"episodes": episodes, "successes": ok, "success_rate": ok / episodes}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="1 recording (video), 2 per expert")
    parser.add_argument("--out", type=Path, help=out_help("sim_record.json"))
    args = parser.parse_args()
    n_record, n_expert = (1, 2) if args.quick else (5, 100)

    res = {
        "quick": args.quick,
        "machine": f"{platform.machine()}, {torch.get_num_threads()} torch threads",
        "image_size": 224,
        "cameras": list(CAMERA_NAMES),
    }
    res.update(bench_physics_and_render(2 if args.quick else 10))
    res["record_video"] = bench_record(n_record, use_videos=True)
    if not args.quick:  # the same function with PNG images: left out of the smoke run (10 s more)
        res["record_images"] = bench_record(n_record, use_videos=False)
    res["experts"] = bench_experts(n_expert)

    print(f"{'measure':<38}{'value':>14}")
    print(f"{'physics, ms per 10 Hz step':<38}{res['physics_ms_per_step']:>14.1f}")
    print(f"{'render 3 cams RGB+depth, ms/timestep':<38}{res['render_ms_per_timestep']:>14.1f}")
    for key in ("record_video", "record_images"):
        if key in res:
            r = res[key]
            print(
                f"{key.replace('_', ' ') + ', timesteps/s':<38}{r['timesteps_per_s']:>14.2f}"
                f"   ({r['timesteps']} timesteps, {r['mb_per_episode']:.1f} MB/episode)"
            )
    for task, r in res["experts"].items():
        print(
            f"{'expert success, ' + task:<38}{100 * r['success_rate']:>13.0f}%   ({r['successes']}/{r['episodes']})"
        )
    write_result(res, args.out or default_out("sim_record.json", args.quick))


if __name__ == "__main__":
    main()
