"""Policy robustness under camera perturbation: the paper's first experiment, in simulation.

    python benchmarks/policy_robustness.py [--quick] [--work DIR] [--steps N] ...

Stages (each is skipped when its output already exists in ``--work``, so a stopped run
resumes where it was; a ``--work`` made with other settings is refused):

1. record ``--demos`` scripted demonstrations of ``--task`` at ``--size`` px (run seed
   ``--seed``; lossless PNG frames, calibration and depth sidecars);
2. write the GenSplat settings beside the dataset and build its Gaussian cache: RGB-D
   reconstruction of the left + right cameras; the policy's external cameras (left by
   default) are replaced with probability ``--probability`` (default 0.25) by a view from
   the training range (|theta| <= 30 deg, 0.5-6 cm), one camera per trajectory,
   ``--views-per-source`` (default 3) distinct cameras per source trajectory;
3. train Diffusion Policy twice with LeRobot's stock trainer through ``policies/train.sh``
   (``baseline`` and ``gensplat``, the latter with the one added line): same data, seed,
   steps, batch and policy settings; the policy sees ``--cameras`` and the robot state;
4. evaluate both checkpoints in ``PerturbedCameraEnv`` with the left external camera
   perturbed once per episode at none / small / medium / large. Episode layouts come from
   the evaluation stream (never a training layout) and both policies meet the same layouts,
   perturbations and sampling noise (torch is seeded per episode).

Defaults, sized for this 2-core CPU, about 2.2 hours (measured: 1.29 s per training step
without GenSplat and 1.45 s with it, 54 and 60 min per policy, evaluation 11 min in two
processes at 0.07-0.08 s per control step, recording 5 min; ``timing`` in the result holds the
measured values): the ``reach_solo`` task (bring the open gripper 2 cm above the one 5 cm
cube on the table, placed at random; the policy must find it in the image), 300
demonstrations at 96x96, the policy sees the left camera and the state; Diffusion Policy as
in ``policies/diffusion.json`` (ResNet-18 encoder from scratch, U-Net ``down_dims``
64-128-256, horizon 16, 8 executed actions) with 1 observation step, DDIM and 10 inference
steps; 2500 steps at batch 32 (warm-up a tenth of the steps, at most 500); 50 evaluation
episodes per level of at most 50 control steps (the demonstrations take 15-18). Harder
tasks did not train at this budget: ``reach`` (a 4 cm cube among two distractors of random
colours) stayed at about 10 % success at every level, and ``pick_place`` (``--cameras
left,right,wrist``) lifted no cube after 1500 steps at batch 8 (see the README);
``--device cuda --steps 20000`` is the setting to aim for on a GPU. Measured on one
H100 machine (16 cores): with ``--parallel-train --workers 6`` each policy ran at 3-4 steps/s,
bound by the dataloader (LeRobot decoding PNG frames), so 20000 steps take about 1.5 h there.
``--baseline-from RESULT.json`` reuses the baseline of an earlier result instead of training
and evaluating it again (an hour here): the evaluation is seeded and reproducible, so its
episode records stand for the checkpoint. The settings that shape the baseline and its
evaluation must match (checked), and the result names the file in ``settings``.
``--quick`` (a few minutes): 2 demos, 4 steps at batch 4, a smaller U-Net, 2 episodes per
level of at most 20 steps: it checks the pipeline end to end, its success rates mean nothing.

Writes ``benchmarks/results/policy_robustness.json`` (``policy_robustness_quick.json`` with
``--quick``): ``{"baseline": {level: success %}, "gensplat": {...}, "episodes_per_level": n,
"progress": {mode: {level: {lift_percent, median_reach_cm}}}, "difference": {level: {points,
ci95, a_only, b_only, mcnemar_p}}, "quick": bool, "settings", "timing", "episodes"}``.
``difference`` compares the two policies episode by episode (they met the same episodes):
GenSplat minus baseline in points, a paired-bootstrap 95 % interval, and an exact McNemar
test on the episodes only one of them solved. ``progress`` tells
apart policies that do not succeed yet: the share of episodes that lifted the cube (pick
and place) and the median closest approach of the pinch point to the cube's centre (to the
reach goal in a reach).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
import torch

os.environ.setdefault("HF_HUB_OFFLINE", "1")

from gensplat_lerobot import prepare
from plotting import Panel, line_panels

from gensplat_transforms.sim.evaluate import EvalConfig, PerturbedCameraEnv, evaluate, paired_difference
from gensplat_transforms.sim.policy_adapter import LeRobotPolicy
from gensplat_transforms.sim.record import RecordConfig, record
from gensplat_transforms.sim.tasks import TASKS
from gensplat_transforms.sim.world import CAMERA_NAMES, EXTERNAL_CAMERAS, STATE_NAMES, WorldConfig
from gensplat_transforms.transform import GenSplatConfig

LEVELS = ("none", "small", "medium", "large")
MODES = ("baseline", "gensplat")
ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"


def repo_id(task: str) -> str:
    return f"gensplat/sim_{task}"


#: (full, quick) defaults of the settings that size the experiment.
DEFAULTS = {
    "demos": (300, 2), "size": (96, 96), "steps": (2500, 4), "batch_size": (32, 4), "workers": (2, 0),
    "down_dims": ("64,128,256", "32,64,128"), "episodes": (50, 2), "max_steps": (None, 20),
}  # fmt: skip


#: Settings that shape the recorded data and the trained policies (kept in ``work/settings.json``).
RUN_SETTINGS = ("task", "cameras", "demos", "size", "steps", "batch_size", "workers", "down_dims",
                "n_obs_steps", "views_per_source", "probability", "fill_holes", "seed", "device")  # fmt: skip


def check_work(work: Path, args) -> None:
    """Record the run settings in ``work``, or refuse to resume a ``work`` made with others."""
    settings = {k: list(v) if isinstance(v, tuple) else v for k in RUN_SETTINGS for v in [getattr(args, k)]}
    path = work / "settings.json"
    if path.is_file():
        old = json.loads(path.read_text())
        changed = {k: (old.get(k), v) for k, v in settings.items() if old.get(k) != v}
        if changed:
            raise SystemExit(f"{work} holds a run with other settings {changed} (was, now): "
                             "pass a new --work or delete it")  # fmt: skip
        return
    work.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=2) + "\n")


def policy_config(work: Path, args) -> Path:
    """``policies/diffusion.json`` with the policy's inputs limited to ``args.cameras`` and
    the state, written to ``work/diffusion.json``."""
    config = json.loads((ROOT / "policies" / "diffusion.json").read_text())
    features = {f"observation.images.{c}": {"type": "VISUAL", "shape": [3, args.size, args.size]}
                for c in args.cameras}  # fmt: skip
    features["observation.state"] = {"type": "STATE", "shape": [len(STATE_NAMES)]}
    config["policy"]["input_features"] = features
    path = work / "diffusion.json"
    path.write_text(json.dumps(config, indent=2) + "\n")
    return path


def train(mode: str, root: Path, out: Path, args) -> dict:
    """Train one policy with ``policies/train.sh diffusion <mode>`` unless ``out`` holds a
    finished run; returns {"seconds", "s_per_step" (start-up included), "last_loss"}, kept in
    ``train_<mode>.json`` beside ``out`` so that a resumed run still reports them."""
    record = out.parent / f"train_{mode}.json"
    if (out / "checkpoints" / "last" / "pretrained_model" / "config.json").is_file():
        return json.loads(record.read_text()) if record.is_file() else {}
    shutil.rmtree(out, ignore_errors=True)  # an unfinished run: lerobot-train refuses existing folders
    dims = "[" + args.down_dims + "]"
    cmd = [
        "bash", str(ROOT / "policies" / "train.sh"), str(policy_config(out.parent, args)), mode,
        f"--dataset.repo_id={repo_id(args.task)}", f"--dataset.root={root}", f"--output_dir={out}",
        f"--steps={args.steps}", f"--batch_size={args.batch_size}", f"--num_workers={args.workers}",
        f"--seed={args.seed}", f"--save_freq={args.steps}", f"--log_freq={max(1, args.steps // 50)}",
        f"--policy.down_dims={dims}", f"--policy.n_obs_steps={args.n_obs_steps}",
        "--policy.noise_scheduler_type=DDIM", f"--policy.num_inference_steps={args.inference_steps}",
        f"--policy.scheduler_warmup_steps={min(500, args.steps // 10)}",
        f"--policy.device={args.device}",
    ]  # fmt: skip
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    out.parent.mkdir(parents=True, exist_ok=True)
    log = out.parent / f"train_{mode}.log"
    t0 = time.perf_counter()
    with open(log, "w") as f:
        run = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, env=env, check=False)
    seconds = time.perf_counter() - t0
    if run.returncode != 0:
        raise RuntimeError(f"training {mode} failed (exit {run.returncode}); see {log}")
    losses = re.findall(r"\bloss:([0-9.]+)", log.read_text())
    print(f"trained {mode} in {seconds:.0f} s, last logged loss {losses[-1] if losses else '?'}", flush=True)
    timing = {"seconds": round(seconds, 1), "s_per_step": round(seconds / args.steps, 2),
              "last_loss": float(losses[-1]) if losses else None}  # fmt: skip
    record.write_text(json.dumps(timing))
    return timing


def evaluate_level(checkpoint: Path, level: str, args) -> dict:
    """Evaluate one checkpoint at one level (one torch thread): {"success" %, "progress"
    ({lift_percent, median_reach_cm}), "episodes" (per-episode records), "seconds",
    "steps"}."""
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    policy = LeRobotPolicy(checkpoint, device=args.device)
    env = PerturbedCameraEnv(EvalConfig(args.task, level, ("left",), seed=args.seed, max_steps=args.max_steps,
                                        world=WorldConfig(height=args.size, width=args.size)))  # fmt: skip
    try:
        result = evaluate(policy, env, args.episodes, reset=policy.reset)
    finally:
        env.close()
    episodes = [{"level": level, "episode": i, "success": s, "steps": n, "reach_m": round(r, 4), "lifted": lf, **p}
                for i, (s, n, p, r, lf) in enumerate(zip(result.successes, result.steps, result.perturbations,
                                                         result.reach_m, result.lifted))]  # fmt: skip
    progress = {"lift_percent": round(100 * result.lift_rate, 2),
                "median_reach_cm": round(100 * float(np.median(result.reach_m)), 2)}  # fmt: skip
    return {"success": round(100 * result.success_rate, 2), "progress": progress, "episodes": episodes,
            "seconds": time.perf_counter() - t0, "steps": sum(result.steps)}  # fmt: skip


def evaluate_all(work: Path, modes: tuple[str, ...], args) -> dict:
    """{mode: {level: evaluate_level(...)}}, ``args.eval_jobs`` (mode, level) pairs at a time
    in separate processes."""
    jobs = [(mode, level) for mode in modes for level in LEVELS]
    with ProcessPoolExecutor(args.eval_jobs, mp_context=multiprocessing.get_context("spawn")) as pool:
        futures = {job: pool.submit(evaluate_level, work / job[0], job[1], args) for job in jobs}
        out: dict = {mode: {} for mode in modes}
        for (mode, level), future in futures.items():
            r = out[mode][level] = future.result()
            print(f"  {mode:>8} {level:>6}: {r['success']:5.1f} % success, {r['progress']['lift_percent']:5.1f} % "
                  f"lifted, median closest approach {r['progress']['median_reach_cm']:.1f} cm over "
                  f"{args.episodes} episodes", flush=True)  # fmt: skip
    return out


#: Settings that shape the baseline policy and its evaluation (``--baseline-from`` checks them).
BASELINE_SETTINGS = ("task", "policy_cameras", "demos", "size", "steps", "batch_size", "workers", "down_dims",
                     "n_obs_steps", "inference_steps", "max_steps", "seed", "device")  # fmt: skip


def reused_baseline(path: Path, settings: dict, episodes: int) -> tuple[dict, dict]:
    """The baseline of an earlier result: ({level: evaluate_level-like record}, its training and
    evaluation timing). Raises SystemExit when its settings differ from ``settings``."""
    old = json.loads(path.read_text())
    if old.get("quick"):
        raise SystemExit(f"--baseline-from {path}: a --quick result is not a baseline")
    changed = {k: (old["settings"].get(k), settings[k]) for k in BASELINE_SETTINGS
               if old["settings"].get(k) != settings[k]}  # fmt: skip
    if old["episodes_per_level"] != episodes:
        changed["episodes"] = (old["episodes_per_level"], episodes)
    if changed:
        raise SystemExit(f"--baseline-from {path}: its baseline was made with other settings {changed} (was, now)")
    per_level = {}
    for level in LEVELS:
        records = sorted((e for e in old["episodes"]["baseline"] if e["level"] == level), key=lambda e: e["episode"])
        if [e["episode"] for e in records] != list(range(episodes)):
            raise SystemExit(f"--baseline-from {path}: episodes 0-{episodes - 1} of level {level} are not all there")
        per_level[level] = {"success": old["baseline"][level], "progress": old["progress"]["baseline"][level],
                            "episodes": records}  # fmt: skip
    timing = {k: old["timing"][k] for k in ("train_baseline", "eval_baseline")}
    return per_level, timing


def paired_by_level(evaluated: dict) -> dict:
    """{level: paired_difference(baseline, gensplat)}: both met the same episodes."""
    def successes(mode: str, level: str) -> list[bool]:
        return [e["success"] for e in evaluated[mode][level]["episodes"]]

    return {lv: paired_difference(successes("baseline", lv), successes("gensplat", lv)) for lv in LEVELS}


def plot(result: dict, path: Path) -> None:
    """Two panels against the level: success % and the median closest approach (cm)."""
    colours = {"baseline": (214, 39, 40), "gensplat": (44, 160, 44)}
    x_ticks = list(enumerate(LEVELS))
    success = {m: [(j, result[m][lv], f"{result[m][lv]:.0f}") for j, lv in x_ticks] for m in MODES}
    reach = {m: [(j, result["progress"][m][lv]["median_reach_cm"], "") for j, lv in x_ticks] for m in MODES}
    top = max(5.0, max(y for pts in reach.values() for _, y, _ in pts))
    top = float(np.ceil(top / 5) * 5)
    x_range = (-0.5, len(LEVELS) - 0.5)
    panels = [
        Panel("success (%)", success, x_range, (0, 100), x_ticks, [(t, str(t)) for t in range(0, 101, 20)]),
        Panel("median closest approach (cm)", reach, x_range, (0, top), x_ticks,
              [(t, f"{t:.0f}") for t in np.arange(0, top + 1e-9, 5)]),
    ]  # fmt: skip
    s = result["settings"]
    note = (f"{s['task']}, Diffusion Policy, {s['steps']} steps at batch {s['batch_size']}, "
            f"{result['episodes_per_level']} episodes per level, left camera perturbed")  # fmt: skip
    line_panels(path, panels, colours, note)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny end-to-end check (a few minutes)")
    parser.add_argument(
        "--work", type=Path, help="dataset, checkpoints, logs (default outputs/policy_robustness[_quick])"
    )
    parser.add_argument("--task", default="reach_solo", choices=sorted(TASKS), help="default reach_solo")
    parser.add_argument("--cameras", default="left",
                        help="comma-separated cameras the policy sees (default left; all: left,right,wrist)")  # fmt: skip
    parser.add_argument("--demos", type=int, help="demonstrations (default 300; quick 2)")
    parser.add_argument("--size", type=int, help="image size of every camera (default 96)")
    parser.add_argument("--steps", type=int, help="training steps per policy (default 2500; quick 4)")
    parser.add_argument("--batch-size", type=int, help="default 32; quick 4")
    parser.add_argument("--workers", type=int, help="dataloader workers (default 2; quick 0)")
    parser.add_argument("--down-dims", help="U-Net widths (default 64,128,256; quick 32,64,128)")
    parser.add_argument("--n-obs-steps", type=int, default=1, help="observation frames per step (default 1)")
    parser.add_argument("--inference-steps", type=int, default=10, help="DDIM steps per action chunk")
    parser.add_argument("--views-per-source", type=int, default=3, help="GenSplat cameras per trajectory")
    parser.add_argument("--probability", type=float, default=0.25,
                        help="chance that GenSplat replaces a sample's camera (default 0.25)")  # fmt: skip
    parser.add_argument("--fill-holes", action=argparse.BooleanOptionalAction, default=True,
                        help="GenSplat fills uncovered pixels from their surroundings (default; "
                        "--no-fill-holes paints them black)")  # fmt: skip
    parser.add_argument("--episodes", type=int, help="evaluation episodes per level (default 50; quick 2)")
    parser.add_argument("--max-steps", type=int, help="evaluation step budget (default the task's; quick 20)")
    parser.add_argument("--seed", type=int, default=0, help="seeds recording, training and evaluation")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--eval-jobs", type=int, default=2, help="evaluation processes (default 2)")
    parser.add_argument(
        "--parallel-train",
        action="store_true",
        help="train both policies at once (a GPU with room to spare; not on a 2-core CPU)",
    )
    parser.add_argument("--baseline-from", type=Path, metavar="RESULT.json",
                        help="reuse the baseline of an earlier result (same settings) instead of training it")  # fmt: skip
    parser.add_argument("--out", type=Path, help="result JSON (default benchmarks/results/policy_robustness.json; "
                        "with --quick policy_robustness_quick.json, so a check never replaces the result)")  # fmt: skip
    args = parser.parse_args()
    for key, (full, quick) in DEFAULTS.items():
        if getattr(args, key) is None:
            setattr(args, key, quick if args.quick else full)
    args.cameras = tuple(args.cameras.split(","))
    if not args.cameras or any(c not in CAMERA_NAMES for c in args.cameras):
        parser.error(f"--cameras: choose from {CAMERA_NAMES}, got {args.cameras}")
    args.max_steps = args.max_steps or TASKS[args.task].max_steps
    args.out = args.out or RESULTS / ("policy_robustness_quick.json" if args.quick else "policy_robustness.json")
    work = args.work or ROOT / "outputs" / ("policy_robustness_quick" if args.quick else "policy_robustness")
    root = work / "dataset"
    replace = tuple(c for c in args.cameras if c in EXTERNAL_CAMERAS)
    gensplat = GenSplatConfig(replace=replace, views_per_source=args.views_per_source,
                              probability=args.probability, fill_holes=args.fill_holes, backend="fast",
                              seed=args.seed)  # fmt: skip
    settings = {k: getattr(args, k) for k in ("demos", "size", "steps", "batch_size", "workers", "down_dims",
                                             "n_obs_steps", "inference_steps", "views_per_source", "max_steps",
                                             "seed", "device", "parallel_train")}  # fmt: skip
    settings.update(task=args.task, policy_cameras=list(args.cameras),
                    policy="diffusion (policies/diffusion.json + the overrides above)",
                    perturbed_camera="left", gensplat={"cameras": list(gensplat.cameras), "replace": list(replace),
                    "probability": gensplat.probability, "level": gensplat.level, "mode": gensplat.mode,
                    "fill_holes": gensplat.fill_holes})  # fmt: skip
    modes, reused, timing = MODES, {}, {}
    if args.baseline_from:
        modes = ("gensplat",)
        reused["baseline"], timing = reused_baseline(args.baseline_from, settings, args.episodes)
        settings["baseline_from"] = args.baseline_from.name
    check_work(work, args)
    t_start = time.perf_counter()

    if not (root / "meta" / "info.json").is_file():
        shutil.rmtree(root, ignore_errors=True)
        res = record(RecordConfig(root, args.task, args.demos, args.seed, use_videos=False, repo_id=repo_id(args.task),
                                  world=WorldConfig(height=args.size, width=args.size)), progress=False)  # fmt: skip
        print(
            f"recorded {res.episodes} demonstrations, {res.frames} frames, in {res.seconds:.0f} s", flush=True
        )
    prepare(root, repo_id(args.task), gensplat, progress=False)

    rates, progress, episodes = {}, {}, {}
    with ThreadPoolExecutor(len(modes) if args.parallel_train else 1) as pool:  # each trains in a subprocess
        for mode, t in zip(modes, pool.map(lambda m: train(m, root, work / m, args), modes)):
            timing[f"train_{mode}"] = t
    print(f"evaluating ({args.eval_jobs} processes)", flush=True)
    t0 = time.perf_counter()
    evaluated = evaluate_all(work, modes, args)
    timing["eval_seconds"] = round(time.perf_counter() - t0, 1)
    for mode, per_level in evaluated.items():
        seconds, steps = (sum(r[k] for r in per_level.values()) for k in ("seconds", "steps"))
        timing[f"eval_{mode}"] = {"process_seconds": round(seconds, 1), "s_per_control_step": round(seconds / steps, 3)}
    timing["total_seconds"] = round(time.perf_counter() - t_start, 1)
    evaluated = {**reused, **evaluated}
    for mode in MODES:
        rates[mode] = {lv: r["success"] for lv, r in evaluated[mode].items()}
        progress[mode] = {lv: r["progress"] for lv, r in evaluated[mode].items()}
        episodes[mode] = [e for r in evaluated[mode].values() for e in r["episodes"]]
    result = {**rates, "episodes_per_level": args.episodes, "quick": args.quick, "progress": progress,
              "difference": paired_by_level(evaluated),
              "settings": settings, "timing": timing, "episodes": episodes}  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    plot(result, args.out.with_suffix(".png"))
    print(f"{'success %':>10}" + "".join(f"{lv:>9}" for lv in LEVELS))
    for mode in MODES:
        print(f"{mode:>10}" + "".join(f"{rates[mode][lv]:9.1f}" for lv in LEVELS))
    diff = result["difference"]
    print(f"{'difference':>10}" + "".join(f"{diff[lv]['points']:+9.1f}" for lv in LEVELS)
          + "  (gensplat - baseline, points; 95% CI " + ", ".join(
              f"{lv} [{diff[lv]['ci95'][0]:+.0f}, {diff[lv]['ci95'][1]:+.0f}]" for lv in LEVELS) + ")")  # fmt: skip
    print(
        f"wrote {args.out} ({timing['total_seconds']:.0f} s{', QUICK: not a result' if args.quick else ''})"
    )


if __name__ == "__main__":
    main()
