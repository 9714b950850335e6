"""The benchmark scripts run end to end in their smoke mode (tiny sizes): a changed signature
in the package breaks them here, not in a user's hands."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def smoke(script: str, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "benchmarks"), str(ROOT / "integrations"), str(ROOT)]),
           "HF_HUB_OFFLINE": "1", "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}  # fmt: skip
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args], capture_output=True, text=True,
                         env=env, cwd=ROOT, timeout=600, check=False)  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    return run


def test_training_step_quick():
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed")
    pytest.importorskip("mujoco", reason="recording needs the 'sim' extra")
    out = ROOT / "outputs" / "training_step_quick.json"
    out.unlink(missing_ok=True)
    smoke("training_step.py", "--quick")
    result = json.loads(out.read_text())
    (row,) = result["rows"]
    assert row["fast_rows"] and row["item_ms"] > 0 and row["updt_s"] > 0 and row["s_per_step"] > 0


def test_render_speed_quick(tmp_path):
    out = tmp_path / "render_speed.json"
    smoke("render_speed.py", "--quick", "--out", str(out))
    result = json.loads(out.read_text())
    assert result["ms_1thread"] > 0 and result["psnr_vs_reference_db"] > 30  # the fast backend agrees
    assert set(result["time_split_ms"]["1thread"]) == {"projection", "binning", "raster", "total"}
