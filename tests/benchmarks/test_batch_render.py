"""benchmarks/batch_render.py times render_batch on a collated batch and says what it rendered."""

from __future__ import annotations

import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import batch_render


def test_quick_run_records_the_render_time_and_what_was_rendered(tmp_path, monkeypatch):
    out = tmp_path / "batch_render.json"
    monkeypatch.setattr(sys, "argv", ["batch_render.py", "--quick", "--profile", "--probability", "1", "--out", str(out)])
    batch_render.main()
    result = json.loads(out.read_text())
    assert result["augmented"] == result["batch_size"] == 4
    assert result["views_rendered"] == 4 * 2 * 2  # samples x stack frames x replaced cameras
    assert len(result["batch_render_runs_ms"]) == 2 and min(result["batch_render_runs_ms"]) > 0
    assert result["worker_ms_one_thread"] > 0
    assert result["profile"] and all(op["self_ms"] >= 0 for op in result["profile"])
