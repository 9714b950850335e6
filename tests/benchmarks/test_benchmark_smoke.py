"""The benchmark scripts run end to end in their smoke mode (``--quick``: tiny sizes, seconds
each): a changed signature in the package breaks them here, not in a user's hands.

Each test runs one script of benchmarks/ in a subprocess with ``--quick --out`` into its
``tmp_path`` (a quick run never writes into benchmarks/results/; without ``--out`` it writes
under outputs/benchmarks_quick/) and checks what the result holds, not only the exit code.
Temporary folders the scripts make go under ``tmp_path`` too (``TMPDIR``). Tested elsewhere:
batch_render.py (tests/benchmarks/test_batch_render.py runs its quick mode), policy_robustness.py and
policy_units.py (their own tests); machine.py, plotting.py and standard_scene.py are helper
modules. gpu_checks.sh runs on CUDA machines only.

The module is marked ``slow`` (``pytest -m "not slow"`` leaves it out): about 5 minutes on a
2-core CPU, 4:43 beside another training job with the DROID sample absent (real_geometry.py adds
30 s); self_calibration.py (four estimates), monocular_path.py (two) and training_throughput.py
(two lerobot-train runs) take about 45-60 s each.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import gensplat_sim  # noqa: F401  (selects MuJoCo's headless backend before mujoco loads)
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
DROID_DIR = ROOT.parent / "shared" / "data" / "droid_sample"  # as conftest.py's
LEVELS = {"none", "small", "medium", "large", "extreme"}

pytestmark = pytest.mark.slow


def smoke(script: str, *args: str, tmp: Path | None = None, env: dict | None = None,
          returncode: int = 0) -> subprocess.CompletedProcess:
    """Run ``benchmarks/<script> args`` from the repository root; it must exit with
    ``returncode`` (default: succeed). Temporary
    folders go under ``tmp``. OpenMP (torch's default threads) gets one thread: beside another
    busy process, two threads waiting on each other made a 4 s script take 24 s (what a script
    sets explicitly still holds)."""
    path = os.pathsep.join([str(ROOT / "benchmarks"), str(ROOT / "integrations"), str(ROOT)])
    env = {**os.environ, "PYTHONPATH": path, "HF_HUB_OFFLINE": "1", "OMP_NUM_THREADS": "1",
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
           **({"TMPDIR": str(tmp)} if tmp else {}), **(env or {})}  # fmt: skip
    cmd = ["bash" if script.endswith(".sh") else sys.executable, str(ROOT / "benchmarks" / script), *args]
    run = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT, timeout=600, check=False)
    assert run.returncode == returncode, run.stdout[-2000:] + run.stderr[-3000:]
    return run


def quick(script: str, tmp_path: Path, *args: str, name: str | None = None) -> dict:
    """``script --quick --out tmp_path/...`` and the JSON it wrote: ``--out`` names the file, or
    with ``name`` the folder that gets ``name``."""
    out = tmp_path / "out" / (name or Path(script).with_suffix(".json").name)
    smoke(script, "--quick", "--out", str(out.parent if name else out), *args, tmp=tmp_path)
    return json.loads(out.read_text())


def positive(*values) -> bool:
    return all(isinstance(v, int | float) and math.isfinite(v) and v > 0 for v in values)


def needs_sim() -> None:
    pytest.importorskip("mujoco", reason="the sim extra is not installed (pip install -e '.[sim]')")


def needs_lerobot() -> None:
    pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")


# core: the package alone


def test_render_speed(tmp_path):
    result = quick("render_speed.py", tmp_path)
    assert result["quick"] and positive(result["ms_1thread"], result["ms_2threads"], result["reference_ms"])
    assert result["psnr_vs_reference_db"] > 30  # the fast backend agrees with the reference
    assert set(result["time_split_ms"]["1thread"]) == {"projection", "binning", "raster", "total"}
    gsplat = result["gsplat"]
    assert gsplat["available"] or "needs CUDA and the gsplat package" in gsplat["reason"]  # it says why not


def test_accuracy_vs_time(tmp_path):
    result = quick("accuracy_vs_time.py", tmp_path, name="accuracy_vs_time.json")
    rows = result["rows"]
    assert {r["knob"] for r in rows} == {"resolution", "density", "sh_degree", "prune", "storage", "backend"}
    assert all(positive(r["ms"], r["num_gaussians"]) and 0 < r["ssim"] <= 1 for r in rows)
    full = next(r for r in rows if (r["knob"], r["setting"]) == ("backend", "fast"))
    assert full["psnr_db"] is None and full["ssim"] == 1.0  # the full-quality render against itself
    assert all(r["psnr_db"] > 15 for r in rows if r["psnr_db"] is not None)
    assert (tmp_path / "out" / "accuracy_vs_time.png").stat().st_size > 0  # the plot beside the JSON


def test_cache_read(tmp_path):
    result = quick("cache_read.py", tmp_path)
    assert set(result["ms_per_read"]) == {"warm_words", "warm_depth", "cold_words", "cold_depth"}
    assert positive(*result["ms_per_read"].values(), result["bytes_per_frame"])
    assert result["episodes"] == 2 and all(len(r) == 1 for r in result["rounds_ms"].values())


def test_depth_registration(tmp_path):
    result = quick("depth_registration.py", tmp_path)
    rows = result["rows"]
    assert set(rows) == {"raw", "registered", "true"} and result["scenes"] == 1
    assert rows["true"]["median_error_m"] == 0
    assert rows["registered"]["median_error_m"] < rows["raw"]["median_error_m"]
    assert all(0 < r["coverage"] <= 1 and positive(r["psnr_medium"], r["psnr_large"]) for r in rows.values())
    assert positive(result["register_ms"], *result["render_ms"].values())


def test_geometry_build(tmp_path):
    """Runs on the CPU in quick mode (the full configuration needs CUDA)."""
    result = quick("geometry_build.py", tmp_path)
    assert result["device"] == ("cuda" if torch.cuda.is_available() else "cpu")
    assert result["config"] == "small"
    rows = result["rows"]
    assert [r["batch_timesteps"] for r in rows] == [1, 2, "auto"]
    assert all("error" not in r and positive(r["ms_per_timestep"], r["timesteps_per_s"]) for r in rows)


def test_geometry_resolution(tmp_path):
    result = quick("geometry_resolution.py", tmp_path)
    assert [r["max_pixels"] for r in result["rows"]] == [None, 12_544]
    for r in result["rows"]:
        assert positive(r["cpu_s"], r["absrel"], r["psnr_large"], r["psnr_large_small"])
        assert 0 < r["delta1"] <= 1
    assert result["rows"][1]["model_size"] == [112, 112]


def test_geometry_speed(tmp_path):
    result = quick("geometry_speed.py", tmp_path)
    devices = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
    assert [(r["config"], r["device"]) for r in result["rows"]] == [("small", d) for d in devices]
    assert all(positive(r["predict_depth_s"], r["assemble_ms"], r["parameters_m"]) for r in result["rows"])


def test_model_quality(tmp_path):
    result = quick("model_quality.py", tmp_path)
    assert positive(*result["model"]["geometry"].values())
    views = result["model"]["novel_views"]
    assert set(views) == {"gensplat", "gensplat_similarity", "rgbd"}
    assert all(set(levels) == LEVELS - {"extreme"} for levels in views.values())
    assert all(positive(m["psnr"], m["depth_mae_m"]) for levels in views.values() for m in levels.values())
    assert positive(result["timing"]["gensplat_ms_per_timestep"], result["timing"]["rgbd_ms_per_timestep"])


def test_real_geometry(tmp_path):
    pytest.importorskip("skimage", reason="the Middlebury pair needs scikit-image (the bench extra)")
    if not (DROID_DIR / "transforms.json").is_file():
        pytest.skip(f"real DROID sample not found: expected {DROID_DIR} (the shared folder beside the repo)")
    result = quick("real_geometry.py", tmp_path, "--droid", str(DROID_DIR), name="real_geometry.json")
    middlebury = result["middlebury"]["calibration"]
    assert "refused" in middlebury["depth"]  # a rectified pair: depth alone cannot give the focal length
    for case in ("depth_focal_given", "depth_focal_principal_point_given", "rgb_focal_and_distance_given"):
        assert middlebury[case]["rotation_error_deg"] < 1 and middlebury[case]["matches"] >= 30
    assert result["droid"]["calibration"]["rgb_focal_and_distance_given"]["matches"] >= 30
    for pair in ("middlebury", "droid"):
        assert math.isfinite(result[pair]["model"]["rotation_error_deg"])
    assert result["settings"]["droid_size"] == [640, 360]


def test_real_nvs(tmp_path):
    pytest.importorskip("skimage", reason="the Middlebury pair needs scikit-image (the bench extra)")
    result = quick("real_nvs.py", tmp_path)
    [scale] = result["scales"].values()
    rows = scale["rows"]
    assert {"source_image", "forward_warp", "rgbd"} <= rows.keys() and 0.5 < scale["warp_coverage"] < 1
    assert rows["forward_warp"]["psnr_warp"] > rows["source_image"]["psnr_warp"] + 5  # the pair moves the view
    for name in result["settings"]:
        filled, black = rows[name]["fill"]["true"], rows[name]["fill"]["false"]
        assert filled["psnr_all"] > black["psnr_all"] and rows[name]["render_ms"] > 0


# the LeRobot extra


def test_cache_check(tmp_path):
    needs_lerobot()
    result = quick("cache_check.py", tmp_path)
    ms = result["ms_per_episode"]
    assert set(ms) == {"headers", "first_check", "indexed", "digest_read", "digest_memo"}
    assert positive(*ms.values(), result["index_bytes_per_episode"])
    assert result["episodes"] == 4 and result["frames_per_episode"] == 2


# the sim extra (and the LeRobot extra where the script records or reads datasets)


def test_sim_record(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("sim_record.py", tmp_path)
    assert positive(result["physics_ms_per_step"], result["render_ms_per_timestep"])
    assert result["record_video"]["episodes"] == 1 and positive(result["record_video"]["timesteps_per_s"])
    assert result["experts"] and all(0 <= r["success_rate"] <= 1 and r["episodes"] == 2
                                     for r in result["experts"].values())  # fmt: skip


def test_camera_motion(tmp_path):
    needs_sim()
    needs_lerobot()  # the arms come from policy_robustness.py
    result = quick("camera_motion.py", tmp_path)
    rows = result["rows"]
    assert {"paper/large", "vista/arc_90deg", "fov/zoom", "train/gensplat", "train/perspective"} <= set(rows)
    assert rows["paper/large"]["moves"] == 2 and rows["train/gensplat"]["moves"] == 6  # 3 views per episode
    assert rows["paper/large"]["shift_pct_median"] > rows["paper/none"]["shift_pct_median"] == 0
    assert rows["train/perspective"]["view_change_deg_median"] is None  # an image warp moves no camera


def test_cache_build(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("cache_build.py", tmp_path, "--root", str(tmp_path / "ds"))
    best = {r["mode"]: r for r in result["best"]}
    assert [(r["mode"], r["processes"]) for r in result["best"]] == [("link", 1), ("copy", 2)]
    for r in best.values():
        assert positive(r["timesteps_per_s"], r["timesteps_per_cpu_s"], r["bytes_per_timestep"])
    assert best["copy"]["bytes_per_timestep"] > best["link"]["bytes_per_timestep"]  # a copy stores the depth
    assert result["dataset"]["episodes"] == 2 and result["dataset"]["resolution"] == [32, 32]
    droid = result["droid_size"]
    assert all(positive(droid[r]["bytes_per_timestep"]) for r in ("rgbd", "geometry", "gensplat"))
    assert set(result["build_memory"]["peak_resident_growth_mb"]) == {"2", "4"}


def test_dataloader(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("dataloader.py", tmp_path)
    assert positive(result["samples_per_s_plain"], result["samples_per_s_gensplat"], result["transform_ms"])
    steps = {"frame_decode", "cache_read", "assemble", "render", "to_uint8", "transform_total"}
    assert set(result["split_ms"]) == steps
    sizes = [result[f"{k}_bytes_per_timestep"] for k in ("cache", "copied_depth", "gaussians_encoding")]
    assert positive(*sizes, *result["dataset_bytes_per_timestep"].values())
    for fidelity in (result["cache_fidelity"], result["copied_depth_fidelity"]):
        assert fidelity["psnr_cached_db"] > 15 and abs(fidelity["psnr_lost_db"]) < 1


def test_nvs_fidelity(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("nvs_fidelity.py", tmp_path, name="nvs_fidelity.json")
    assert result["unavailable"] == {}  # the shipped weights: the model's methods ran
    methods = set(result) - {"unavailable", "settings"}
    assert {"rgbd", "rgbd_sensor", "forward_warp", "gensplat_small", "homography"} <= methods
    for levels in (result[m] for m in methods):
        assert set(levels) == LEVELS and all(e["n"] > 0 and 0 < e["ssim"] <= 1 for e in levels.values())
    assert result["source_image"]["none"]["psnr"] is None  # the source view is the truth at "none"
    assert positive(result["rgbd"]["large"]["psnr"], result["rgbd"]["large"]["ms"])
    assert (tmp_path / "out" / "nvs_fidelity.png").stat().st_size > 0


def test_nvs_warp_gap(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("nvs_warp_gap.py", tmp_path, name="nvs_warp_gap.json")
    assert {"forward_warp", "forward_warp_left", "rgbd", "rgbd_left", "rgbd_edge_scale_1"} <= set(result)
    assert set(result["edge_share"]) == LEVELS and all(0 <= s <= 1 for s in result["edge_share"].values())
    assert all(positive(result["rgbd"][lv]["interior"]) for lv in LEVELS - {"none"})


def test_render_scale(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("render_scale.py", tmp_path)
    scales = result["scales"]
    assert list(scales) == ["1.0", "0.75", "0.5", "0.35", "0.25"] and result["frame_size"] == [320, 240]
    assert scales["0.5"]["render_size"] == [160, 120] and scales["1.0"]["psnr_vs_full_frame"] is None
    assert all(positive(r["ms"], r["psnr_frame"], r["ssim_frame"]) for r in scales.values())
    assert result["views_compared"] == 2 * result["samples"] == 8


def test_self_calibration(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("self_calibration.py", tmp_path, name="self_calibration.json")
    assert set(result) == {"depth", "sensor_depth", "rgb_given_fov", "rgb_model", "settings"}
    for variant in ("depth", "sensor_depth", "rgb_given_fov", "rgb_model"):
        r = result[variant]
        assert r["rotation_error_deg"] < 5 and r["matches"] >= 30 and max(r["focal_error"]) < 0.2
        assert set(r["novel_views"]) == LEVELS and positive(r["novel_views"]["large"]["estimated"]["psnr"])
    assert "estimated_geometry" in result["rgb_model"]["novel_views"]["large"]


def test_monocular_path(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("monocular_path.py", tmp_path, name="monocular_path.json")
    assert set(result) == {"perfect", "noisy", "network_cost", "settings"}
    perfect, noisy = result["perfect"], result["noisy"]
    assert perfect["max_lookup_distance"] == 0 == noisy["max_lookup_distance"]  # the oracle found every image
    # the truth through MoGe-2's focal recovery: the focal lengths exact, the pose as well as the matches allow
    assert max(perfect["focal_error"]) < 1e-3 and perfect["rotation_error_deg"] < 2 and perfect["scale_error"] < 0.05
    for level in LEVELS - {"none"}:
        nv = perfect["novel_views"][level]
        assert abs(nv["monocular"]["psnr"] - nv["rgbd_true"]["psnr"]) < 1.0  # true depth through the RGB-only path
        assert nv["monocular_unaligned"] == nv["monocular"]  # perfect scales: the alignment changes nothing
        assert positive(noisy["novel_views"][level]["monocular"]["psnr"])
    assert noisy["scale_noise"] > 0 and noisy["novel_views"]["large"]["monocular_unaligned"] != \
        noisy["novel_views"]["large"]["monocular"]


def test_training_step(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("training_step.py", tmp_path)
    (row,) = result["rows"]
    assert row["fast_rows"] and positive(row["item_ms"], row["updt_s"], row["s_per_step"])


def test_policy_update(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("policy_update.py", tmp_path)
    rows = result["rows"]
    assert [r["name"] for r in rows][:3] == ["the study (96 px)", "80 px", "64 px"] and len(rows) == 5
    assert rows[0]["of_study"] == 1.0 and not any(r["compiled"] for r in rows)  # --compile not given
    for r in rows:
        assert positive(r["encoder_forward_s"], r["unet_forward_s"], r["backward_s"], r["optimiser_s"])
        assert r["encoder_forward_s"] + r["unet_forward_s"] <= r["forward_s"]
        assert r["update_s"] == pytest.approx(r["forward_s"] + r["backward_s"] + r["optimiser_s"])


def test_policy_update_refuses_no_timed_update(tmp_path):
    needs_sim()
    needs_lerobot()
    run = smoke("policy_update.py", "--steps", "0", "--out", str(tmp_path / "r.json"), tmp=tmp_path, returncode=2)
    assert "--steps 0: at least one timed update" in run.stderr and not (tmp_path / "r.json").exists()


def test_training_throughput(tmp_path):
    needs_sim()
    needs_lerobot()
    result = quick("training_throughput.py", tmp_path)
    rows = result["rows"]
    assert result["complete"] and positive(rows["plain"]["samples_per_s"], rows["worker"]["samples_per_s"])
    assert 0 <= rows["worker"]["augmented_share"] <= 1 and rows["plain"]["of_plain"] == 1.0
    if torch.cuda.is_available():
        assert positive(rows["batch"].get("samples_per_s", 0)), rows["batch"]
    else:  # the GPU row says why it is missing
        assert "no CUDA device" in rows["batch"]["missing"]
    assert set(result["loader"]["ms_per_sample"]) == {"plain", "batch", "worker"}
    assert positive(*result["loader"]["ms_per_sample"].values())


# CUDA


def test_gpu_checks(tmp_path):
    if not torch.cuda.is_available():
        pytest.skip("gpu_checks.sh runs on CUDA only (torch.cuda.is_available() is False)")
    pytest.importorskip("gsplat", reason="gpu_checks.sh needs the gsplat extra")
    smoke("gpu_checks.sh", tmp=tmp_path, env={"OUT": str(tmp_path / "out"), "QUICK": "1"})
    (batch,) = (tmp_path / "out").glob("batch_render_*.json")
    assert json.loads(batch.read_text())["device"] != "cpu"
    (build,) = (tmp_path / "out").glob("geometry_build_*.json")
    rows = json.loads(build.read_text())["rows"]
    assert rows and all("error" not in r and positive(r["ms_per_timestep"]) for r in rows)
