"""benchmarks/training_throughput.py refuses datasets that would measure the wrong thing."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import training_throughput as tt


@pytest.fixture(scope="module")
def small(scene_dataset):
    """One episode of 6 frames at 16x16 (shared: read only)."""
    return scene_dataset(tt.REPO, episodes=1, frames=6, size=16)


def run_main(monkeypatch, *argv: str) -> str:
    monkeypatch.setattr(sys, "argv", ["training_throughput.py", *argv])
    with pytest.raises(SystemExit) as exit_:
        tt.main()
    return str(exit_.value)


def test_an_epoch_shorter_than_the_workers_is_refused(small, monkeypatch):
    message = run_main(monkeypatch, "--root", str(small), "--size", "16", "--batch-size", "4", "--workers", "2")
    assert "6 frames: 1 batches of 4 per epoch" in message and "Record more episodes" in message


def test_a_recording_of_another_size_is_refused(small, monkeypatch):
    message = run_main(monkeypatch, "--root", str(small), "--size", "32", "--batch-size", "1", "--workers", "0")
    assert "16x16 images, not --size 32" in message


def test_lerobot_log_lines_give_the_window_and_the_step_split():
    line = ("INFO 2026-11-26 16:36:56 ot_train.py:641 step:30 smpl:2K ep:32 epch:2.44 loss:1.047 grdn:4.482 "
            "lr:3.1e-06 updt_s:1.200 data_s:2.195 smp/s:19 mem_gb:13.18")  # fmt: skip
    (stamp, step, update_s, data_s), = tt.LOG_LINE.findall(line)
    assert (step, update_s, data_s) == ("30", "1.200", "2.195")
    assert tt.log_time("2026-11-26 16:37:47") - tt.log_time(stamp) == 51


def test_gpu_busy_averages_the_samples_inside_the_window(monkeypatch):
    readings = iter([10.0, 30.0, 50.0, 70.0] + [90.0] * 1000)
    monkeypatch.setattr(tt.torch.cuda, "utilization", lambda: next(readings))
    with tt.GpuBusy(period=0.001) as busy:
        while len(busy.samples) < 5:
            pass
    assert [b for _, b in busy.samples[:4]] == [10.0, 30.0, 50.0, 70.0]
    times = [t for t, _ in busy.samples]
    assert busy.mean(times[1], times[2]) == 40.0
    assert busy.mean(times[-1] + 1, times[-1] + 2) is None


def test_gpu_busy_without_nvml_has_no_samples(monkeypatch, capsys):
    def no_nvml():
        raise ModuleNotFoundError("pynvml module not found")

    monkeypatch.setattr(tt.torch.cuda, "utilization", no_nvml)
    with tt.GpuBusy(period=0.001) as busy:
        busy._thread.join(timeout=10)  # the sampler gives up at its first reading
    assert busy.samples == [] and busy.mean(0, float("inf")) is None
    assert "GPU utilisation not sampled: pynvml module not found" in capsys.readouterr().err


def test_rows_of_a_run_cut_short_say_what_is_missing():
    plain = {"samples_per_s": 40.0, "update_s": 0.1, "data_s": 1.5}
    rows = tt.rows_of({"plain": [plain, {**plain, "samples_per_s": 38.0}], "worker": [], "batch": []},
                      {"batch": "lerobot-train (batch) failed"}, cuda=True)  # fmt: skip
    assert rows["plain"]["samples_per_s_runs"] == [40.0, 38.0] and rows["plain"]["of_plain"] == 1.0
    assert rows["worker"] == {"missing": "not run yet"}
    assert rows["batch"] == {"failed": "lerobot-train (batch) failed"}
    assert "no CUDA device" in tt.rows_of({"plain": [plain], "worker": []}, {}, cuda=False)["batch"]["missing"]


def test_modes_must_start_with_plain(small, monkeypatch, capsys):
    assert run_main(monkeypatch, "--root", str(small), "--modes", "worker,plain") == "2"
    assert "--modes: plain first, then worker and/or batch; got worker,plain" in capsys.readouterr().err


def test_loader_cost_times_every_mode_on_the_same_batches(small, tmp_path):
    """The loader-side cost runs each mode's items (GenSplat in batch mode carrying its
    BATCH_KEYS) over the same batches and reports each against plain."""
    import shutil

    from gensplat_lerobot import load_settings, prepare

    from gensplat_transforms.transform import GenSplatConfig

    root = tmp_path / "ds"
    shutil.copytree(small, root)
    prepare(root, tt.REPO, GenSplatConfig(probability=1.0), progress=False)
    config, reconstructor = load_settings(root)
    policy = Path(tt.__file__).parents[1] / "policies" / "diffusion.json"
    cost = tt.loader_cost(root, policy, config, reconstructor, ["plain", "batch", "worker"], 2, 2, 2)
    assert set(cost["ms_per_sample"]) == {"plain", "batch", "worker"} and cost["samples_per_round"] == 4
    assert all(len(runs) == 2 and min(runs) > 0 for runs in cost["rounds_ms"].values())
    assert cost["of_plain"]["plain"] == 1.0
    ratios = sorted(p / w for p, w in zip(cost["rounds_ms"]["plain"], cost["rounds_ms"]["worker"]))
    assert cost["of_plain"]["worker"] == round(sum(ratios) / 2, 3)  # the median of two rounds
