"""benchmarks/policy_units.py: a unit whose file holds the current settings is skipped, any
other is run and written; the summary's statistics, read from made-up unit files."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import gensplat_sim  # noqa: F401  (selects the headless GL backend before MuJoCo loads)
import numpy as np
import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
pytest.importorskip("mujoco", reason="the study needs the 'sim' extra (mujoco)")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import policy_robustness as pr
import policy_units as pu

from gensplat_transforms.core.atomic import atomic_write_json

TASK = "reach_solo"
LEVELS = [(p, lv) for p, levels in pr.PROTOCOLS.items() for lv in levels]


def unit_file(unit: pu.Unit, wins: dict, episodes: int = 4, wall: float = 100.0, settings: dict | None = None,
              train: dict | None = None, share: float | None = None) -> dict:
    """A made-up unit file: ``wins`` {(protocol, level): (episodes,) successes}, 0 where absent."""
    success = {p: {} for p in pr.PROTOCOLS}
    records = {p: [] for p in pr.PROTOCOLS}
    for p, lv in LEVELS:
        won = np.asarray(wins.get((p, lv), np.zeros(episodes)), dtype=bool)
        success[p][lv] = 100 * float(won.mean())
        records[p] += [{"level": lv, "episode": i, "success": bool(w)} for i, w in enumerate(won)]
    return {"unit": {"task": unit.task, "arm": unit.arm, "seed": unit.seed, "name": unit.name},
            "settings": settings or {"episodes": episodes}, "commit": "c0ffee", "success": success,
            "episodes": records, "timing": {"wall_seconds": wall, **({"train": train} if train else {}),
                                            **({"machine_share": share} if share is not None else {})}}  # fmt: skip


def write(results: Path, unit: pu.Unit, **kwargs) -> None:
    atomic_write_json(unit.path(results), unit_file(unit, **kwargs))


def test_units_done_are_skipped_and_the_others_run(tmp_path, monkeypatch, capsys):
    results, work = tmp_path / "results", tmp_path / "work"
    units = {arm: pu.Unit(TASK, arm, 1) for arm in ("baseline", "perspective", "gensplat", "gensplat-tilt")}
    current = {arm: pu.unit_settings(u, pu.unit_args(u, work)) for arm, u in units.items()}
    assert current["baseline"]["augmentation"] == {"train_seed": 1}  # seed 1 trains the replicate baseline@s1
    assert current["gensplat"] != current["gensplat-tilt"]
    write(results, units["baseline"], wins={}, settings=current["baseline"])  # done
    write(results, units["perspective"], wins={}, settings={**current["perspective"], "steps": 1})  # stale
    units["gensplat"].path(results).write_text('{"unit": ')  # a stopped write of another tool: unreadable
    assert [pu.state(u, current[a], results) for a, u in units.items()] == ["done", "stale", "unreadable", "missing"]

    ran = []

    def run_unit(unit, args):
        ran.append(unit.name)
        assert args.work == work / TASK and args.steps == 5000 and args.episodes == 50
        return unit_file(unit, wins={("paper", "none"): [1, 1, 0, 1]}, settings=pu.unit_settings(unit, args))

    monkeypatch.setattr(pu, "run_unit", run_unit)
    pu.main(["run", "--tasks", TASK, "--seeds", "1", "--results", str(results), "--work", str(work)])
    assert ran == ["perspective@s1", "gensplat@s1", "gensplat-tilt@s1"]
    assert [pu.state(u, current[a], results) for a, u in units.items()] == ["done"] * 4
    ran.clear()
    pu.main(["run", "--tasks", TASK, "--seeds", "1", "--results", str(results), "--work", str(work)])
    assert ran == []  # a second run (a fresh machine with the committed files) trains nothing
    assert "none 75 %" in capsys.readouterr().out


def test_status_says_what_a_stopped_run_left_to_resume(tmp_path, capsys):
    """``status`` names each unfinished unit's last checkpoint in the work folder (what the next
    ``run`` resumes from), a finished training left to evaluate, and a damaged step file."""
    work = tmp_path / "work"

    def checkpoint(arm: str, text: str) -> None:
        last = work / TASK / f"{arm}@s1" / "checkpoints" / "last"
        (last / "pretrained_model").mkdir(parents=True)
        (last / "training_state").mkdir()
        (last / "pretrained_model" / "train_config.json").write_text("{}")
        (last / "training_state" / "training_step.json").write_text(text)

    checkpoint("perspective", '{"step": 1500}')
    checkpoint("gensplat", '{"step": 5000}')
    checkpoint("gensplat-tilt", '{"step": "500"}')
    pu.main(["status", "--tasks", TASK, "--seeds", "1", "--results", str(tmp_path / "results"), "--work", str(work)])
    said = dict(line.split(": ", 1) for line in capsys.readouterr().out.splitlines())
    said = {name.split()[-1]: state for name, state in said.items()}  # by unit
    assert said["baseline@s1"] == "missing"
    assert said["perspective@s1"] == "missing (trained to step 1500 of 5000; the next run resumes there)"
    assert said["gensplat@s1"] == "missing (trained; its evaluation is left)"
    assert said["gensplat-tilt@s1"].startswith("missing (") and "no step count" in said["gensplat-tilt@s1"]


def test_a_failed_unit_does_not_stop_the_others(tmp_path, monkeypatch, capsys):
    """A unit that fails (an error, or its task's folder held by another run) is reported and the
    run goes on to the next units; it ends with an error naming the failed ones."""
    results, work, ran = tmp_path / "results", tmp_path / "work", []

    def run_unit(unit, args):
        ran.append(unit.name)
        if unit.arm == "baseline":
            raise SystemExit(f"{args.work} is in use by another policy_robustness.py run")
        if unit.arm == "gensplat":
            raise RuntimeError("evaluation crashed")
        return unit_file(unit, wins={}, settings=pu.unit_settings(unit, args))

    monkeypatch.setattr(pu, "run_unit", run_unit)
    with pytest.raises(SystemExit, match="2 unit\\(s\\) failed: reach_solo baseline@s1, reach_solo gensplat@s1"):
        pu.main(["run", "--tasks", TASK, "--seeds", "1", "--results", str(results), "--work", str(work)])
    assert ran == ["baseline@s1", "perspective@s1", "gensplat@s1", "gensplat-tilt@s1"]
    assert pu.Unit(TASK, "gensplat-tilt", 1).path(results).exists() and not pu.Unit(TASK, "gensplat", 1).path(results).exists()
    assert "gensplat@s1: failed: RuntimeError: evaluation crashed" in capsys.readouterr().err


def test_a_unit_holds_its_task_folder_only_while_it_runs(tmp_path, monkeypatch):
    """Units of one task run one after another in one process (``run --arms baseline,gensplat``):
    each takes the task's work folder, and gives it back when it ends, also when it fails."""
    ran = []

    def fake(unit, args):
        with pytest.raises(SystemExit, match="in use by another"):
            pr.lock_work(args.work)  # held while the unit runs
        ran.append(unit.name)
        if unit.arm == "perspective":
            raise RuntimeError("training failed")
        return {}

    monkeypatch.setattr(pu, "_run_unit", fake)
    units = [pu.Unit(TASK, arm, 1) for arm in ("baseline", "gensplat", "perspective")]
    for unit in units[:2]:
        assert pu.run_unit(unit, pu.unit_args(unit, tmp_path / "work")) == {}
    with pytest.raises(RuntimeError, match="training failed"):
        pu.run_unit(units[2], pu.unit_args(units[2], tmp_path / "work"))
    assert ran == [u.name for u in units]
    os.close(pr.lock_work(tmp_path / "work" / TASK))  # free after each


@pytest.mark.parametrize("argv, message", [
    (["run", "--tasks", "fly"], "--tasks: unknown"), (["run", "--arms", "magic"], "--arms: unknown"),
    (["run", "--seeds", "x"], "--seeds: integers"), (["run", "--seeds", "-1"], "each in 0-99"),
])  # fmt: skip
def test_bad_command_lines_are_refused(argv, message, capsys):
    with pytest.raises(SystemExit):
        pu.parse_args(argv)
    assert message in capsys.readouterr().err


def test_summary_statistics_paired_over_seeds_and_episodes(tmp_path):
    results = tmp_path / "results"
    base = {0: [1, 0, 0, 1, 0, 0, 0, 0], 1: [1, 1, 0, 0, 0, 0, 0, 0]}  # large: 25 % on each seed
    for seed, won in base.items():
        write(results, pu.Unit(TASK, "baseline", seed), wins={("paper", "large"): won}, episodes=8)
        write(results, pu.Unit(TASK, "perspective", seed), wins={("paper", "large"): won}, episodes=8)  # the same
        write(results, pu.Unit(TASK, "gensplat", seed), wins={(p, lv): [1] * 8 for p, lv in LEVELS}, episodes=8,
              wall=4000.0 if seed else 100.0)  # fmt: skip
    write(results, pu.Unit(TASK, "gensplat-tilt", 0), wins={("paper", "large"): [1, 1, 1, 1, 0, 0, 0, 0]}, episodes=8)
    s = pu.summarise(TASK, results)
    assert s["arms"] == ["baseline", "perspective", "gensplat", "gensplat-tilt"] and s["best_2d"] == "perspective"
    assert s["success"]["baseline"]["paper"]["large"] == {"mean": 25.0, "per_seed": {0: 25.0, 1: 25.0}}
    vs = s["difference"]["vs_baseline"]
    assert vs["perspective"]["paper"]["large"] == {"points": 0.0, "ci95": [0.0, 0.0], "seeds": [0, 1]}
    big = vs["gensplat"]["paper"]["large"]
    assert big["points"] == 75.0 and 50 <= big["ci95"][0] < 75 < big["ci95"][1] <= 100
    assert vs["gensplat"]["paper"]["none"] == {"points": 100.0, "ci95": [100.0, 100.0], "seeds": [0, 1]}
    # one seed in common: tilt - baseline on seed 0 is (4 - 2) / 8 = +25 points
    tilt = vs["gensplat-tilt"]["paper"]["large"]
    assert tilt["points"] == 25.0 and tilt["seeds"] == [0] and tilt["ci95"][0] < 25 < tilt["ci95"][1]
    assert s["difference"]["vs_best_2d"]["gensplat"]["paper"]["large"]["points"] == 75.0
    assert s["units"]["gensplat@s1"] == {"wall_seconds": 4000.0, "within_limit": False}
    assert pu.summarise(TASK, results) == s  # the bootstrap is seeded
    table = pu.markdown(s)
    assert "| gensplat | 0,1 | 100 (+100 [+100, +100])" in table and "| gensplat - perspective |" in table
    assert "(1 over 60 min)." in table and "resumed" not in table
    write(results, pu.Unit(TASK, "gensplat-tilt", 1), wins={}, episodes=8, train={"resumed_from_step": 1500})
    s = pu.summarise(TASK, results)
    assert s["units"]["gensplat-tilt@s1"] == {"wall_seconds": 100.0, "within_limit": True, "resumed_from_step": 1500}
    assert "gensplat-tilt@s1 resumed a stopped training" in pu.markdown(s)


def test_the_summary_leaves_out_stale_and_unreadable_unit_files_and_names_them(tmp_path):
    """A unit file made with other settings (the study changed since) is not comparable: the
    summary leaves it out and says so, as it does an unreadable one; without ``current`` every
    readable file counts."""
    results = tmp_path / "results"
    for seed in (0, 1):
        write(results, pu.Unit(TASK, "baseline", seed), wins={("paper", "none"): [1, 1, 1, 1]},
              settings={"episodes": 4, "steps": 5000 if seed == 0 else 2500})  # fmt: skip
    atomic_write_json(pu.Unit(TASK, "gensplat", 0).path(results), {"unit": {"arm": "gensplat", "seed": 0}})
    current = lambda unit: {"episodes": 4, "steps": 5000}
    s = pu.summarise(TASK, results, current=current)
    assert s["success"]["baseline"]["paper"]["none"]["per_seed"] == {0: 100.0}
    assert s["left_out"] == {"baseline@s1.json": "stale", "gensplat@s0.json": "unreadable"}
    assert "baseline@s1.json (stale), gensplat@s0.json (unreadable)." in pu.markdown(s)
    everything = pu.summarise(TASK, results)
    assert set(everything["success"]["baseline"]["paper"]["none"]["per_seed"]) == {0, 1}
    assert everything["left_out"] == {"gensplat@s0.json": "unreadable"}


def test_the_summary_command_compares_each_file_with_the_current_settings(tmp_path, monkeypatch, capsys):
    """``summary`` leaves out the files ``run`` would call stale, as ``run`` computes the
    settings, and says so on stderr."""
    results, work = tmp_path / "results", tmp_path / "work"
    units = [pu.Unit(TASK, "baseline", 0), pu.Unit(TASK, "baseline", 1)]
    current = [pu.unit_settings(u, pu.unit_args(u, work)) for u in units]
    write(results, units[0], wins={("paper", "none"): [1, 1, 1, 0]}, settings=current[0])
    write(results, units[1], wins={}, settings={**current[1], "steps": 2500})
    tables = []
    monkeypatch.setattr(pu, "write_readme", tables.append)
    pu.main(["summary", "--results", str(results), "--work", str(work)])
    assert f"policy_units: {TASK}/baseline@s1.json left out of the summary: stale" in capsys.readouterr().err
    summary = (results / TASK / "summary.json").read_text()
    assert '"baseline@s1.json": "stale"' in summary and "| baseline | 0 | 75 |" in tables[0]


def test_the_summary_says_what_share_of_the_machine_the_slow_units_had(tmp_path):
    results = tmp_path / "results"
    write(results, pu.Unit(TASK, "baseline", 0), wins={}, wall=7000.0, share=0.6)
    write(results, pu.Unit(TASK, "baseline", 1), wins={}, wall=5000.0, share=0.45)
    write(results, pu.Unit(TASK, "gensplat", 0), wins={}, wall=3000.0, share=0.9)  # within the limit: not counted
    write(results, pu.Unit(TASK, "gensplat", 1), wins={}, wall=8000.0)  # an older file without it
    s = pu.summarise(TASK, results)
    assert s["units"]["baseline@s1"] == {"wall_seconds": 5000.0, "within_limit": False, "machine_share": 0.45}
    assert "machine_share" not in s["units"]["gensplat@s1"]
    assert "(3 over 60 min); the units over the limit that recorded it had 45%-60% of the machine's cores." in pu.markdown(s)
    write(results, pu.Unit(TASK, "baseline", 0), wins={}, wall=7000.0, share=0.45)  # one share: no range
    assert "recorded it had 45% of the machine's cores." in pu.markdown(pu.summarise(TASK, results))


def test_cpu_seconds_count_ended_children_and_the_share_is_of_all_cores():
    before = pu.cpu_seconds()
    subprocess.run([sys.executable, "-c", "import time\nt = time.process_time()\nwhile time.process_time() - t < 0.3: pass"],
                   check=True)  # fmt: skip
    assert pu.cpu_seconds() - before >= 0.25
    assert pu.machine_share(60.0, 60.0, cores=2) == 0.5 and pu.machine_share(0.0, 0.0, cores=2) == 0.0
    assert pu.machine_share(120.0, 60.0) == round(2.0 / os.cpu_count(), 2)


def test_a_unit_records_the_torch_and_lerobot_that_ran_it():
    import lerobot
    import torch

    assert pu.versions() == {"torch": torch.__version__, "lerobot": lerobot.__version__}


def test_the_bootstrap_interval_covers_the_truth_at_its_rate():
    """Paired seeds x episodes with a true difference of +20 points: the 95 % interval holds it
    in about 95 % of repeated studies."""
    rng = np.random.default_rng(1)
    hits = 0
    for _ in range(200):
        b = {s: rng.random(50) < 0.4 for s in range(3)}
        a = {s: rng.random(50) < 0.6 for s in range(3)}
        lo, hi = pu.paired(a, b, rng, resamples=400)["ci95"]
        hits += lo <= 20 <= hi
    assert 0.88 <= hits / 200 <= 0.995


def test_summary_rewrites_only_the_readme_between_its_markers(tmp_path):
    readme = tmp_path / "README.md"
    readme.write_text(f"# B\n\nbefore\n{pu.MARKERS[0]}\nold table\n{pu.MARKERS[1]}\nafter\n")
    pu.write_readme("| new |\n", readme)
    assert readme.read_text() == f"# B\n\nbefore\n{pu.MARKERS[0]}\n| new |\n{pu.MARKERS[1]}\nafter\n"


def test_the_plot_names_each_arms_seeds(tmp_path, monkeypatch):
    results = tmp_path / "results"
    for arm, seed in (("baseline", 0), ("baseline", 1), ("gensplat", 1)):
        write(results, pu.Unit(TASK, arm, seed), wins={("paper", "large"): [1, 0, 1, 1]})
    summary = pu.summarise(TASK, results)
    pu.plot(summary, tmp_path / "summary.png")
    assert (tmp_path / "summary.png").read_bytes().startswith(b"\x89PNG")
    drawn = {}
    monkeypatch.setattr(pu, "line_panels", lambda path, panels, colours, *a, **k: drawn.update(colours=colours, panels=panels))
    pu.plot(summary, tmp_path / "again.png")
    assert list(drawn["colours"]) == ["baseline (seeds 0,1)", "gensplat (seeds 1)"]
    large = drawn["panels"][0].series["gensplat (seeds 1)"][pr.PROTOCOLS["paper"].index("large")]
    assert large[1] == 75.0  # the mean over the arm's seeds


def test_the_summary_reads_each_target_met_missed_or_not_measured(tmp_path, monkeypatch):
    """Each of the study's targets is read from the summary with its figure and the seeds it
    rests on: met, missed (a figure below it, or an interval reaching zero), or not measured
    while an arm it needs has no unit; final only once every seed is in."""
    results = tmp_path / "results"
    n = 10
    for seed in (0, 1):  # baseline: 90 % at none, 20 % at large; GenSplat: 80 % at none, 60 % at large
        write(results, pu.Unit(TASK, "baseline", seed), wins={("paper", "none"): [1] * 9 + [0],
              ("paper", "large"): [1] * 2 + [0] * 8}, episodes=n, wall=100.0 if seed else 5000.0)  # fmt: skip
        write(results, pu.Unit(TASK, "gensplat", seed), wins={("paper", "none"): [1] * 8 + [0] * 2,
              ("paper", "large"): [1] * 6 + [0] * 4}, episodes=n)  # fmt: skip
    base, large, none, time = pu.summarise(TASK, results)["targets"]
    assert [base["target"], large["target"], none["target"]] == [t.text for t in pu.TARGETS[TASK]]
    assert base == {"target": base["target"], "figure": 90.0, "ci95": None, "seeds": [0, 1], "status": "met", "final": False}
    assert large["figure"] == 40.0 and large["ci95"][0] > 0 and large["status"] == "met"
    assert none["figure"] == -10.0 and none["status"] == "missed"  # below baseline - 3
    assert time["figure"] == 1 and time["units"] == 4 and time["status"] == "missed" and not time["final"]
    table = pu.markdown(pu.summarise(TASK, results))
    assert "- baseline >= 80 % at the training camera: 90 % (seeds 0,1): met" in table
    assert "- every unit within 60 min of wall time: 1 of 4 units over: missed" in table

    write(results, pu.Unit(TASK, "gensplat", 1), wins={("paper", "large"): [1] * 5 + [0] * 5}, episodes=n)  # +30 on seed 1
    large = pu.summarise(TASK, results)["targets"][1]
    assert large["figure"] == 35.0 and large["ci95"][0] > 0 and large["status"] == "met"
    write(results, pu.Unit(TASK, "gensplat", 0), wins={("paper", "large"): [1] * 2 + [0] * 8}, episodes=n)  # +0 on seed 0
    large = pu.summarise(TASK, results)["targets"][1]
    assert large["figure"] == 15.0 and large["status"] == "missed"  # under +20
    for seed in (0, 1):  # +30 on seed 0 as well, but the interval reaches below zero: missed all the same
        write(results, pu.Unit(TASK, "baseline", seed), wins={("paper", "large"): [1] * 7 + [0] * 3}, episodes=n)
        write(results, pu.Unit(TASK, "gensplat", seed), wins={("paper", "large"): [0] * 7 + [1] * 3}, episodes=n)
    flip = pu.Target("made up", "gensplat", "large", -100, "baseline", interval=True)
    monkeypatch.setitem(pu.TARGETS, TASK, (flip,))
    row = pu.summarise(TASK, results)["targets"][0]
    assert row["figure"] == -40.0 and row["ci95"][0] < 0 and row["status"] == "missed"
    monkeypatch.undo()

    write(results, pu.Unit(TASK, "baseline", 2), wins={("paper", "none"): [1] * n}, episodes=n)
    base = pu.summarise(TASK, results)["targets"][0]
    assert base["seeds"] == [0, 1, 2] and base["final"]
    write(results, pu.Unit(TASK, "baseline", 7), wins={("paper", "none"): [1] * n}, episodes=n)  # a seed beyond the study's
    base = pu.summarise(TASK, results)["targets"][0]
    assert base["seeds"] == [0, 1, 2, 7] and base["final"]

    marked = tmp_path / "marked"
    write(marked, pu.Unit("reach_marked", "gensplat", 0), wins={("paper", "large"): [1] * n}, episodes=n)
    rows = pu.summarise("reach_marked", marked)["targets"]
    assert [r["status"] for r in rows] == ["not measured", "not measured", "met"]  # no baseline, no 2D arm yet
    assert "- baseline >= 60 % at the training camera: no unit yet: not measured" in pu.markdown(pu.summarise("reach_marked", marked))
    write(marked, pu.Unit("reach_marked", "perspective", 0), wins={("paper", "large"): [1] * 5 + [0] * 5}, episodes=n)
    assert pu.summarise("reach_marked", marked)["targets"][1]["figure"] == 50.0  # GenSplat - the best 2D arm
