"""The policy robustness study as units that finish: each unit (task x arm x training seed)
is trained, evaluated and written to its own file, so a stopped run loses only the unit in
flight.

    python benchmarks/policy_units.py run [--tasks T,..] [--arms A,..] [--seeds 0,1,2] [--commit]
    python benchmarks/policy_units.py status     # each unit: done, stale, unreadable or to run (and its checkpoint)
    python benchmarks/policy_units.py summary    # summary.json, plot and README table from the unit files

A unit trains Diffusion Policy on one task with one arm's augmentation and one training seed,
then evaluates it under every protocol of ``policy_robustness.py`` (the paper's four levels,
VISTA's ``small_perturb`` and ``arc_90deg``, ``fov`` ``zoom``) on the same evaluation episodes
as every other unit of its task (the evaluation seed is fixed; seed N > 0 trains the
replicate ``<arm>@s<N>``). Training and evaluation are ``policy_robustness.py``'s own
(``STUDY`` holds its settings per task), run in ``outputs/policy_units/<task>``, where the
recorded dataset, the checkpoints and the evaluated levels stay between runs.

The result of a unit is ``benchmarks/results/policy/<task>/<arm>@s<seed>.json``: the unit, the
settings that shape it, the commit it ran on (and the machine and the versions of torch and
LeRobot that ran it), success % per protocol and level, the
per-episode records, the training and evaluation times, the unit's wall time (the sum of
its stages; evaluated levels kept from a stopped run count their process time shared by the
evaluation processes) and the share of the machine's cores its processes had over the run
(their CPU time over the run's wall time times the cores: well below 1 where other work shared
the machine). ``run`` skips a unit whose file holds the current settings, and with ``--commit``
commits each file the moment its unit ends (that file only); a unit that fails is reported and
the run goes on to the next (the run ends with an error naming the failed units). ``summary``
reads the unit files alone (those made with the current settings; others are named as left
out): per arm the success over its seeds, and each arm against the
baseline and against the best 2D arm, paired on the same seeds and episodes, with a bootstrap
95 % interval over seeds and episodes, and the study's ``TARGETS`` read from them (met, missed or
not measured, on the seeds in so far); it writes ``summary.json`` and ``summary.png`` per task,
and the tables in benchmarks/README.md between the ``policy-units`` markers.
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import policy_robustness as pr
from machine import cpu_model
from plotting import Panel, line_panels

from gensplat_transforms.core.atomic import atomic_write, atomic_write_json, read_json_object

#: policy_robustness.py's settings per task (what its command line would say).
STUDY = {
    "reach_solo": ["--steps", "5000", "--episodes", "50"],
    "reach_marked": ["--steps", "5000", "--episodes", "50"],
}
#: The arms of the study: the baseline, the best 2D arm, the paper's GenSplat arm and a wider sampler.
ARMS = ("baseline", "perspective", "gensplat", "gensplat-tilt")
SEEDS = (0, 1, 2)
UNITS = pr.ROOT / "benchmarks" / "results" / "policy"
WORK = pr.ROOT / "outputs" / "policy_units"
README = pr.ROOT / "benchmarks" / "README.md"
MARKERS = ("<!-- policy-units:begin -->", "<!-- policy-units:end -->")
#: Bootstrap resamples of the summary's intervals.
RESAMPLES = 2000
#: A unit's wall-time limit (s): recorded against each unit in the summary.
UNIT_LIMIT_S = 3600


@dataclass(frozen=True)
class Target:
    """What the study is read against: ``arm``'s success % at ``level`` of the paper's protocol
    (``reference`` None), or its paired difference in points from ``reference`` ("baseline" or
    "best_2d"), at least ``at_least``; with ``interval``, the difference's 95 % interval must
    lie above zero too."""

    text: str
    arm: str
    level: str
    at_least: float
    reference: str | None = None
    interval: bool = False


#: The study's targets per task (each summary says which are met, on which seeds).
TARGETS = {
    "reach_solo": (
        Target("baseline >= 80 % at the training camera", "baseline", "none", 80),
        Target("GenSplat >= baseline + 20 points at Large, interval above zero", "gensplat", "large", 20, "baseline", True),
        Target("GenSplat >= baseline - 3 points at the training camera", "gensplat", "none", -3, "baseline"),
    ),
    "reach_marked": (
        Target("baseline >= 60 % at the training camera", "baseline", "none", 60),
        Target("GenSplat >= best 2D arm + 10 points at Large, interval above zero", "gensplat", "large", 10, "best_2d",
               True),
    ),
}  # fmt: skip


@dataclass(frozen=True)
class Unit:
    task: str
    arm: str
    seed: int

    @property
    def name(self) -> str:
        """The arm as policy_robustness.py names it: ``<arm>``, or the replicate ``<arm>@s<seed>``."""
        return self.arm if self.seed == 0 else f"{self.arm}@s{self.seed}"

    def path(self, units: Path = UNITS) -> Path:
        return units / self.task / f"{self.arm}@s{self.seed}.json"


def unit_args(unit: Unit, work: Path = WORK, extra: tuple[str, ...] = ()):
    """policy_robustness.py's parsed arguments for ``unit`` (``STUDY`` and ``extra`` on top)."""
    return pr.parse_args(["--task", unit.task, "--arms", unit.name, "--work", str(work / unit.task),
                          *STUDY[unit.task], *extra])  # fmt: skip


def unit_settings(unit: Unit, args) -> dict:
    """What shapes a unit's result: the study's settings, its augmentation and its evaluation."""
    settings = pr.result_settings(args)
    return {**{k: settings[k] for k in pr.ARM_SETTINGS}, "augmentation": settings["augmentation"][unit.name],
            "episodes": args.episodes, "protocols": settings["protocols"]}  # fmt: skip


def state(unit: Unit, settings: dict, units: Path = UNITS) -> str:
    """``done`` (its file holds ``settings``), ``stale`` (other settings), ``unreadable`` or ``missing``."""
    path = unit.path(units)
    if not path.exists():
        return "missing"
    data = read_json_object(path)
    if not {"unit", "settings", "success", "episodes"} <= data.keys():
        return "unreadable"
    return "done" if data["settings"] == settings else "stale"


def left_in_work(unit: Unit, args) -> str:
    """What a stopped run of ``unit`` left in its work folder ``args.work`` for the next run to
    resume: its training's last checkpoint, or a finished training; "" when nothing."""
    try:
        steps = pr.trained_steps(args.work / unit.name)
    except SystemExit as e:  # a step file without a step: the run stops there, say so here
        return f" ({e})"
    if steps >= args.steps:
        return " (trained; its evaluation is left)"
    return f" (trained to step {steps} of {args.steps}; the next run resumes there)" if steps else ""


def head_commit() -> str:
    """The commit this code runs on, ``+changes`` when the work tree differs from it."""
    def git(*a: str) -> str:
        return subprocess.run(["git", "-C", str(pr.ROOT), *a], check=False, capture_output=True, text=True).stdout.strip()

    commit = git("rev-parse", "HEAD") or "unknown"
    return commit + ("+changes" if git("status", "--porcelain", "--untracked-files=no") else "")


def versions() -> dict[str, str]:
    """The versions of the libraries that set a unit's numbers and pace: torch (with its build),
    LeRobot."""
    import lerobot
    import torch

    return {"torch": torch.__version__, "lerobot": lerobot.__version__}


def cpu_seconds() -> float:
    """CPU seconds (user + system) of this process and of its children that have ended."""
    own, children = (resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN))
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def machine_share(cpu: float, wall: float, cores: int | None = None) -> float:
    """The share of the machine's ``cores`` (default: all) that ``cpu`` seconds over ``wall``
    seconds are, rounded to 0.01."""
    return round(cpu / (max(wall, 1e-9) * (cores or os.cpu_count() or 1)), 2)


def run_unit(unit: Unit, args) -> dict:
    """Record (once per task), prepare, train and evaluate ``unit``; its result (see the module
    docstring). Holds the task's work folder for the unit's time only, so that the next unit of
    the same task, in this process or another, can take it."""
    lock = pr.lock_work(args.work)
    try:
        return _run_unit(unit, args)
    finally:
        os.close(lock)


def _run_unit(unit: Unit, args) -> dict:
    work, name = args.work, unit.name
    pr.check_work(work, (name,), args)
    stages = {}
    cpu, start = cpu_seconds(), time.perf_counter()
    t0 = time.perf_counter()
    pr.record_dataset(work, args)
    stages["record_seconds"] = round(time.perf_counter() - t0, 1)
    t0 = time.perf_counter()
    pr.prepare_arm(work, name, args)
    stages["prepare_seconds"] = round(time.perf_counter() - t0, 1)
    train = pr.train(name, pr.dataset_root(work, name), work / name, args)
    t0 = time.perf_counter()
    evaluated = pr.evaluate_all(work, (name,), args)
    stages["eval_seconds"] = round(time.perf_counter() - t0, 1)
    records = [r for per_arm in evaluated.values() for r in per_arm[name].values()]
    stages["eval_process_seconds"] = round(sum(r["seconds"] for r in records), 1)
    # levels kept from a stopped run count their process time shared by the evaluation processes
    evaluation = max(stages["eval_seconds"], stages["eval_process_seconds"] / args.eval_jobs)
    wall = stages["record_seconds"] + stages["prepare_seconds"] + train.get("seconds", 0.0) + evaluation
    stages["machine_share"] = machine_share(cpu_seconds() - cpu, time.perf_counter() - start)
    return {
        "unit": {"task": unit.task, "arm": unit.arm, "seed": unit.seed, "name": name},
        "settings": unit_settings(unit, args), "commit": head_commit(), "machine": cpu_model(),
        "versions": versions(),
        "reconstructor": pr.STUDY_RECONSTRUCTOR if pr.arm_kind(name) in pr.GENSPLAT_ARMS else None,
        "success": {p: {lv: r["success"] for lv, r in evaluated[p][name].items()} for p in pr.PROTOCOLS},
        "progress": {p: {lv: r["progress"] for lv, r in evaluated[p][name].items()} for p in pr.PROTOCOLS},
        "timing": {"train": train, **stages, "wall_seconds": round(wall, 1)},
        "episodes": {p: [e for r in evaluated[p][name].values() for e in r["episodes"]] for p in pr.PROTOCOLS},
    }  # fmt: skip


def commit_file(path: Path, message: str) -> None:
    """Commit ``path`` alone on the branch of the repository that holds it (retried while another
    git command holds the index)."""
    for attempt in range(10):
        git = ["git", "-C", str(path.parent)]
        add = subprocess.run([*git, "add", "--", str(path)], check=False, capture_output=True, text=True)
        run = subprocess.run([*git, "commit", "-q", "-m", message, "--", str(path)],
                             check=False, capture_output=True, text=True) if add.returncode == 0 else add  # fmt: skip
        if run.returncode == 0:
            return
        time.sleep(2 + attempt)
    print(f"could not commit {path}: {run.stderr.strip()}", flush=True)


# ---------------------------------------------------------------- summary


def successes(unit_file: dict, protocol: str, level: str) -> np.ndarray:
    """(episodes,) bool of a unit's successes at one level, ordered by episode."""
    eps = sorted((e for e in unit_file["episodes"][protocol] if e["level"] == level), key=lambda e: e["episode"])
    return np.array([e["success"] for e in eps], dtype=bool)


def paired(a: dict[int, np.ndarray], b: dict[int, np.ndarray], rng: np.random.Generator,
           resamples: int = RESAMPLES) -> dict | None:  # fmt: skip
    """``a`` minus ``b`` in points, each {seed: (episodes,) successes}, paired on the seeds both
    hold and on the episodes: the mean difference and a bootstrap 95 % interval that resamples
    the seeds, then the episodes within each (None without a common seed)."""
    seeds = sorted(set(a) & set(b))
    if not seeds:
        return None
    diff = np.stack([a[s].astype(float) - b[s].astype(float) for s in seeds])  # (seeds, episodes)
    n_seeds, n_eps = diff.shape
    pick_seeds = rng.integers(0, n_seeds, (resamples, n_seeds))
    pick_eps = rng.integers(0, n_eps, (resamples, n_seeds, n_eps))
    means = diff[pick_seeds[..., None], pick_eps].mean(axis=(1, 2))
    lo, hi = np.percentile(means, [2.5, 97.5])
    return {"points": round(100 * float(diff.mean()), 2), "ci95": [round(100 * float(lo), 2), round(100 * float(hi), 2)],
            "seeds": seeds}  # fmt: skip


def load_units(task: str, units: Path = UNITS, current: Callable[[Unit], dict] | None = None
               ) -> tuple[dict[str, dict[int, dict]], dict[str, str]]:  # fmt: skip
    """{arm: {seed: unit file}} of ``task``'s unit files that are readable and, where
    ``current`` gives a unit's current settings, hold them; and {file name: why} of the files
    left out (``unreadable``, or ``stale``: made with other settings, so not comparable)."""
    out: dict[str, dict[int, dict]] = {}
    left_out: dict[str, str] = {}
    for path in sorted((units / task).glob("*@s*.json")):
        data = read_json_object(path)
        if not {"unit", "settings", "success", "episodes"} <= data.keys():
            left_out[path.name] = "unreadable"
            continue
        unit = Unit(task, data["unit"]["arm"], int(data["unit"]["seed"]))
        if current is not None and data["settings"] != current(unit):
            left_out[path.name] = "stale"
            continue
        out.setdefault(unit.arm, {})[unit.seed] = data
    return out, left_out


def summarise(task: str, units: Path = UNITS, seed: int = 0, current: Callable[[Unit], dict] | None = None) -> dict:
    """The summary of ``task``'s unit files (see the module docstring); ``seed`` seeds the
    bootstrap; ``current``: a unit's current settings, files with others are left out and named
    (:func:`load_units`)."""
    found, left_out = load_units(task, units, current)
    arms = list(pr.ordered(found))
    rng = np.random.default_rng(seed)
    success = {arm: {p: {lv: {"mean": round(float(np.mean([f["success"][p][lv] for f in found[arm].values()])), 2),
                                 "per_seed": {s: f["success"][p][lv] for s, f in sorted(found[arm].items())}}
                             for lv in levels} for p, levels in pr.PROTOCOLS.items()} for arm in arms}  # fmt: skip
    per_level = {arm: {(p, lv): {s: successes(f, p, lv) for s, f in found[arm].items()}
                       for p, levels in pr.PROTOCOLS.items() for lv in levels} for arm in arms}  # fmt: skip
    perturbed = [(p, lv) for p, levels in pr.PROTOCOLS.items() for lv in levels if lv != "none"]
    two_d = [a for a in pr.TWO_D_ARMS if a in found]
    best_2d = max(two_d, key=lambda a: np.mean([success[a][p][lv]["mean"] for p, lv in perturbed])) if two_d else None

    def against(reference: str | None) -> dict:
        if reference is None:
            return {}
        return {arm: {p: {lv: paired(per_level[arm][p, lv], per_level[reference][p, lv], rng) for lv in levels}
                      for p, levels in pr.PROTOCOLS.items()} for arm in arms if arm != reference}  # fmt: skip

    walls = {f"{arm}@s{s}": f["timing"] for arm in arms for s, f in sorted(found[arm].items())}
    summary = {
        "task": task, "arms": arms, "success": success, "best_2d": best_2d,
        "difference": {"vs_baseline": against("baseline" if "baseline" in found else None),
                       "vs_best_2d": against(best_2d)},
        "units": {name: {"wall_seconds": t["wall_seconds"], "within_limit": t["wall_seconds"] <= UNIT_LIMIT_S}
                  | ({"resumed_from_step": t["train"]["resumed_from_step"]}
                     if "resumed_from_step" in t.get("train", {}) else {})
                  | ({"machine_share": t["machine_share"]} if "machine_share" in t else {})
                  for name, t in walls.items()},
        "commits": sorted({f["commit"] for arm in arms for f in found[arm].values()}),
        "episodes_per_level": sorted({f["settings"]["episodes"] for arm in arms for f in found[arm].values()}),
        "left_out": left_out,
    }  # fmt: skip
    return summary | {"targets": targets(summary)}


def targets(summary: dict) -> list[dict]:
    """Each of the task's ``TARGETS`` read from ``summary``: its figure (success % or paired
    points), interval, the seeds it rests on, and ``status`` "met", "missed" or "not measured"
    (an arm it needs has no unit yet) and ``final``: every seed of ``SEEDS`` is in. Last, the
    unit-time target: ``figure`` of the ``units`` over ``UNIT_LIMIT_S`` (final with every unit in)."""
    out = []
    for t in TARGETS.get(summary["task"], ()):
        row = {"target": t.text, "figure": None, "ci95": None, "seeds": [], "status": "not measured"}
        if t.reference is None:
            found = summary["success"].get(t.arm, {}).get("paper", {}).get(t.level)
            if found:
                row.update(figure=found["mean"], seeds=sorted(int(s) for s in found["per_seed"]))
        else:
            key = "vs_baseline" if t.reference == "baseline" else "vs_best_2d"
            found = summary["difference"][key].get(t.arm, {}).get("paper", {}).get(t.level)
            if found:
                row.update(figure=found["points"], ci95=found["ci95"], seeds=[int(s) for s in found["seeds"]])
        if row["figure"] is not None:
            met = row["figure"] >= t.at_least and (not t.interval or row["ci95"][0] > 0)
            row["status"] = "met" if met else "missed"
        out.append(row | {"final": set(SEEDS) <= set(row["seeds"])})  # an extra seed does not unsettle it
    units = summary["units"]
    over = sum(not u["within_limit"] for u in units.values())
    out.append({"target": f"every unit within {UNIT_LIMIT_S // 60} min of wall time", "figure": over,
                "ci95": None, "seeds": [], "status": ("missed" if over else "met") if units else "not measured",
                "units": len(units), "final": len(units) == len(ARMS) * len(SEEDS)})  # fmt: skip
    return out


def cell(summary: dict, arm: str, protocol: str, level: str) -> str:
    """A table cell: mean success % over the arm's seeds, and its paired difference from the baseline."""
    text = f"{summary['success'][arm][protocol][level]['mean']:.0f}"
    d = summary["difference"]["vs_baseline"].get(arm, {}).get(protocol, {}).get(level)
    return text + (f" ({difference(d['points'], d['ci95'])})" if d else "")


def difference(points: float, ci95: list[float]) -> str:
    """A paired difference as the tables write it: "+46 [+35, +57]"."""
    return f"{points:+.0f} [{ci95[0]:+.0f}, {ci95[1]:+.0f}]"


def markdown(summary: dict) -> str:
    """The task's table: a row per arm (with its seeds), a column per level of every protocol."""
    columns = [(p, lv) for p, levels in pr.PROTOCOLS.items() for lv in levels]
    title = (f"`{summary['task']}`: success % (mean over seeds; in brackets the paired difference from the "
             "baseline in points, bootstrap 95 % interval over seeds and episodes):")
    lines = [title, "",
             "| arm | seeds | " + " | ".join(lv for _, lv in columns) + " |", "|---" * (len(columns) + 2) + "|"]  # fmt: skip
    for arm in summary["arms"]:
        seeds = ",".join(str(s) for s in summary["success"][arm]["paper"]["none"]["per_seed"])
        lines.append(f"| {arm} | {seeds} | " + " | ".join(cell(summary, arm, p, lv) for p, lv in columns) + " |")
    best = summary["best_2d"]
    for arm, diffs in summary["difference"]["vs_best_2d"].items():
        if pr.arm_kind(arm) in pr.GENSPLAT_ARMS:
            row = [diffs[p][lv] for p, lv in columns]
            lines.append(f"| {arm} - {best} | | " + " | ".join(
                difference(d["points"], d["ci95"]) if d else "" for d in row) + " |")  # fmt: skip
    walls = summary["units"]
    if walls:
        longest = max(walls.values(), key=lambda u: u["wall_seconds"])["wall_seconds"]
        over = sum(not u["within_limit"] for u in walls.values())
        resumed = [name for name, u in walls.items() if "resumed_from_step" in u]
        shares = sorted(u["machine_share"] for u in walls.values() if not u["within_limit"] and "machine_share" in u)
        share = "-".join(dict.fromkeys(f"{v:.0%}" for v in shares[:1] + shares[-1:]))  # "45%", "45%-60%"
        counts = "its wall time counts" if len(resumed) == 1 else "their wall times count"
        lines += ["", f"Units: {len(walls)}; the longest took {longest / 60:.0f} min ({over} over {UNIT_LIMIT_S // 60} min)"
                  + (f"; {', '.join(resumed)} resumed a stopped training, and {counts} only the steps after the "
                     "resume" if resumed else "")
                  + (f"; the units over the limit that recorded it had {share} of the machine's cores" if shares else "")
                  + "."]  # fmt: skip
    if summary.get("targets"):
        lines += ["", f"Targets (read on the seeds in so far; final once all of {','.join(map(str, SEEDS))} are):", ""]
        lines += [f"- {t['target']}: {target_figure(t)}: {t['status']}" for t in summary["targets"]]
    if summary.get("left_out"):
        lines += ["", "Left out (not comparable with the current settings, or unreadable): "
                  + ", ".join(f"{name} ({why})" for name, why in summary["left_out"].items()) + "."]  # fmt: skip
    return "\n".join(lines) + "\n"


def target_figure(t: dict) -> str:
    """A target's figure as the table writes it: "87 % (seeds 0,1)", "+46 [+35, +57] (seeds 0,1)",
    "8 of 9 units over", or "no unit yet"."""
    if "units" in t:
        return f"{t['figure']} of {t['units']} units over"
    if t["figure"] is None:
        return "no unit yet"
    seeds = f"(seeds {','.join(map(str, t['seeds']))})"
    if t["ci95"] is None:
        return f"{t['figure']:.0f} % {seeds}"
    return f"{difference(t['figure'], t['ci95'])} {seeds}"


def plot(summary: dict, path: Path) -> None:
    """Success % against the level, a panel per protocol, a line per arm (mean over its seeds,
    which its legend entry names)."""
    names = {a: f"{a} (seeds {','.join(map(str, summary['success'][a]['paper']['none']['per_seed']))})"
             for a in summary["arms"]}  # fmt: skip
    panels = []
    for p, levels in pr.PROTOCOLS.items():
        ticks = list(enumerate(levels))
        series = {names[a]: [(j, summary["success"][a][p][lv]["mean"], "") for j, lv in ticks] for a in summary["arms"]}
        panels.append(Panel(f"success (%), {p}", series, (-0.5, len(levels) - 0.5), (0, 100), ticks,
                            [(t, str(t)) for t in range(0, 101, 20)]))  # fmt: skip
    line_panels(path, panels, {names[a]: pr.colour(a) for a in summary["arms"]},
                f"{summary['task']}, Diffusion Policy, mean over seeds", panel_size=(360, 300))  # fmt: skip


def write_readme(tables: str, readme: Path = README) -> None:
    """Replace the text between ``MARKERS`` in ``readme`` with ``tables``."""
    text = readme.read_text()
    begin, end = (text.index(m) for m in MARKERS)
    atomic_write(readme, lambda tmp: Path(tmp).write_text(text[: begin + len(MARKERS[0])] + "\n" + tables + text[end:]))


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("command", choices=("run", "status", "summary"))
    parser.add_argument("--tasks", default=",".join(STUDY), help=f"comma-separated (default {','.join(STUDY)})")
    parser.add_argument("--arms", default=",".join(ARMS), help=f"comma-separated (default {','.join(ARMS)})")
    parser.add_argument("--seeds", default=",".join(map(str, SEEDS)), help="training seeds (default 0,1,2)")
    parser.add_argument("--commit", action="store_true", help="commit each unit's file when the unit ends")
    parser.add_argument("--results", type=Path, default=UNITS,
                        help="folder of the unit files (default benchmarks/results/policy; another checkout's "
                        "when this one runs from a worktree)")  # fmt: skip
    parser.add_argument("--work", type=Path, default=WORK, help="datasets and checkpoints (default outputs/policy_units)")
    args = parser.parse_args(argv)
    args.tasks = tuple(args.tasks.split(","))
    args.arms = tuple(args.arms.split(","))
    for task in args.tasks:
        if task not in STUDY:
            parser.error(f"--tasks: unknown {task!r}; choose from {tuple(STUDY)}")
    for arm in args.arms:
        if arm not in pr.ARMS:
            parser.error(f"--arms: unknown {arm!r}; choose from {pr.ARMS}")
    try:
        args.seeds = tuple(int(s) for s in args.seeds.split(","))
    except ValueError:
        parser.error(f"--seeds: integers, got {args.seeds!r}")
    if not all(0 <= s < 100 for s in args.seeds):
        parser.error(f"--seeds: each in 0-99, got {args.seeds}")
    return args


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    if args.command == "summary":
        tables = []
        current = lambda unit: unit_settings(unit, unit_args(unit, args.work))  # what `run` compares
        for task in STUDY:
            summary = summarise(task, args.results, current=current)
            for name, why in summary["left_out"].items():
                print(f"policy_units: {task}/{name} left out of the summary: {why}", file=sys.stderr)
            if not summary["arms"]:
                continue
            atomic_write_json(args.results / task / "summary.json", summary)
            plot(summary, args.results / task / "summary.png")
            tables.append(markdown(summary))
            print(tables[-1])
        write_readme("\n".join(tables))
        return
    units, failed = [Unit(t, a, s) for t in args.tasks for s in args.seeds for a in args.arms], []
    for unit in units:
        u_args = unit_args(unit, args.work)
        status = state(unit, unit_settings(unit, u_args), args.results)
        print(f"{unit.task:>13} {unit.name:>18}: {status}{'' if status == 'done' else left_in_work(unit, u_args)}",
              flush=True)  # fmt: skip
        if args.command == "status" or status == "done":
            continue
        t0 = time.perf_counter()
        try:
            result = run_unit(unit, u_args)
        except (Exception, SystemExit) as e:  # noqa: BLE001  (any failure: the other units go on)
            print(f"{unit.task} {unit.name}: failed: {type(e).__name__}: {e}", file=sys.stderr, flush=True)
            failed.append(f"{unit.task} {unit.name}")
            continue
        path = atomic_write_json(unit.path(args.results), result)
        s = result["success"]
        print(f"{unit.task} {unit.name}: none {s['paper']['none']:.0f} %, large {s['paper']['large']:.0f} %, "
              f"unit {result['timing']['wall_seconds'] / 60:.0f} min ({(time.perf_counter() - t0) / 60:.0f} min in this "
              f"run); wrote {path}", flush=True)  # fmt: skip
        if args.commit:
            commit_file(path, f"policy unit {unit.task} {unit.arm} seed {unit.seed}: none "
                        f"{s['paper']['none']:.0f} %, large {s['paper']['large']:.0f} %")  # fmt: skip
    if failed:
        raise SystemExit(f"policy_units: {len(failed)} unit(s) failed: {', '.join(failed)}")


if __name__ == "__main__":
    sys.exit(main())
