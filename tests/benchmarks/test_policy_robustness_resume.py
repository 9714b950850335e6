"""benchmarks/policy_robustness.py resumes a stopped run: a training from its last checkpoint
(a real lerobot-train), an evaluation at the levels it had not finished."""

from __future__ import annotations

import json
import os
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import gensplat_sim  # noqa: F401  (selects the headless GL backend before MuJoCo loads)
import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
pytest.importorskip("mujoco", reason="recording needs the 'sim' extra (mujoco)")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import policy_robustness as pr
from gensplat_sim.record import RecordConfig, record
from gensplat_sim.world import WorldConfig


def test_a_stopped_training_resumes_from_its_last_checkpoint(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setattr(pr, "CHECKPOINT_EVERY", 2)
    quick = ["--quick", "--size", "48", "--work", str(tmp_path)]
    args = pr.parse_args([*quick, "--steps", "4"])
    root, out = tmp_path / "dataset", tmp_path / "baseline"
    record(RecordConfig(root, args.task, args.demos, args.seed, use_videos=False, repo_id=pr.repo_id(args.task),
                        world=WorldConfig(height=48, width=48)), progress=False)  # fmt: skip
    assert pr.trained_steps(out) == 0
    # a run stopped after its checkpoint at step 2: the training of a 2-step run
    first = pr.train("baseline", root, out, pr.parse_args([*quick, "--steps", "2"]))
    assert pr.trained_steps(out) == 2 and "resumed_from_step" not in first
    (tmp_path / "train_baseline.json").unlink()
    timing = pr.train("baseline", root, out, args)
    assert pr.trained_steps(out) == 4 and timing["resumed_from_step"] == 2 and timing["s_per_step"] > 0
    log = (tmp_path / "train_baseline.log").read_text()
    assert "Resuming data order" in log and log.count("Output dir:") == 2  # both runs' output kept
    assert sorted(p.name for p in (out / "checkpoints").iterdir()) == ["000004", "last"]  # the final one kept
    assert json.loads((tmp_path / "train_baseline.json").read_text()) == timing
    assert pr.train("baseline", root, out, args) == timing  # finished: not trained again


def test_a_recording_killed_midway_is_not_taken_for_a_dataset(tmp_path, monkeypatch):
    args = pr.parse_args(["--quick", "--size", "48", "--demos", "2", "--work", str(tmp_path)])

    def killed(config, progress):  # LeRobot writes meta/info.json first, then the episodes
        (config.root / "meta").mkdir(parents=True)
        (config.root / "meta" / "info.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(pr, "record", killed)
    with pytest.raises(KeyboardInterrupt):
        pr.record_dataset(tmp_path, args)
    assert not (tmp_path / "dataset").exists()
    monkeypatch.undo()
    pr.record_dataset(tmp_path, args)  # starts over in a clean partial folder
    root = tmp_path / "dataset"
    assert not (tmp_path / "dataset.partial").exists()
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["total_episodes"] == 2
    texts = [p.read_text(errors="ignore") for p in root.rglob("*.json")]
    assert texts and not any("dataset.partial" in t for t in texts)  # nothing points at the old name


def test_a_damaged_checkpoint_step_is_reported_not_retrained(tmp_path):
    last = tmp_path / "checkpoints" / "last"
    (last / "pretrained_model").mkdir(parents=True)
    (last / "training_state").mkdir()
    assert pr.trained_steps(tmp_path) == 0  # no train_config.json: no checkpoint
    (last / "pretrained_model" / "train_config.json").write_text("{}")
    for text in ('{"step": 1', '{"step": "500"}', "[]"):
        (last / "training_state" / "training_step.json").write_text(text)
        with pytest.raises(SystemExit, match="no step count"):
            pr.trained_steps(tmp_path)
    (last / "training_state" / "training_step.json").write_text('{"step": 500, "batch_size": 32}')
    assert pr.trained_steps(tmp_path) == 500


def test_a_work_folder_takes_one_run_at_a_time(tmp_path, monkeypatch):
    fd = pr.lock_work(tmp_path / "work")
    with pytest.raises(SystemExit, match="in use by another"):
        pr.lock_work(tmp_path / "work")
    argv = ["policy_robustness.py", "--arms", "baseline", "--work", str(tmp_path / "work"), "--out", str(tmp_path / "r.json")]
    monkeypatch.setattr(sys, "argv", argv)
    with pytest.raises(SystemExit, match="in use by another"):  # before it records or trains anything
        pr.main()
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == [".lock"]
    os.close(fd)
    os.close(pr.lock_work(tmp_path / "work"))  # free again


def fake_level(checkpoint: Path, protocol: str, level: str, args) -> dict:
    """An evaluate_level stand-in that records its calls."""
    fake_level.calls.append((checkpoint.name, protocol, level))
    return {"success": 50.0, "progress": {"lift_percent": 0.0, "median_reach_cm": 1.0}, "episodes": [],
            "seconds": 1.0, "steps": 10}  # fmt: skip


def test_a_stopped_evaluation_resumes_at_the_levels_it_had_not_finished(tmp_path, monkeypatch):
    monkeypatch.setattr(pr, "evaluate_level", fake_level)
    monkeypatch.setattr(pr, "ProcessPoolExecutor", lambda jobs, mp_context: ThreadPoolExecutor(jobs))
    model = tmp_path / "gensplat" / "checkpoints" / "last" / "pretrained_model"
    model.mkdir(parents=True)
    (model / "config.json").write_text("{}")
    (model / "model.safetensors").write_bytes(b"weights")
    levels = [(p, lv) for p, lvs in pr.PROTOCOLS.items() for lv in lvs]

    def run(*argv: str) -> list:
        """The levels evaluated (not kept) by one evaluate_all."""
        fake_level.calls = []
        out = pr.evaluate_all(tmp_path, ("gensplat",), pr.parse_args(["--episodes", "3", *argv]))
        assert {(p, lv) for p, lvs in out.items() for lv in lvs["gensplat"]} == set(levels)
        return sorted(fake_level.calls)

    assert run() == sorted(("gensplat", p, lv) for p, lv in levels)
    assert run() == []  # every level kept
    stored = tmp_path / "gensplat" / "evaluation"
    (stored / "vista_arc_90deg.json").unlink()  # stopped before this level finished
    (stored / "paper_none.json").write_text('{"key": ')  # cut short
    record = json.loads((stored / "fov_zoom.json").read_text())
    del record["record"]["episodes"]  # a record without its episodes
    (stored / "fov_zoom.json").write_text(json.dumps(record))
    assert run() == [("gensplat", "fov", "zoom"), ("gensplat", "paper", "none"), ("gensplat", "vista", "arc_90deg")]
    assert len(run("--max-steps", "7")) == len(levels)  # another evaluation setting
    (model / "model.safetensors").write_bytes(b"retrained")
    assert len(run()) == len(levels)  # another checkpoint
    assert json.loads((stored / "fov_zoom.json").read_text())["record"]["success"] == 50.0
