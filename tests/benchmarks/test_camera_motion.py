"""benchmarks/camera_motion.py: the image motion and viewpoint change of the robustness study's
camera moves."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import gensplat_sim  # noqa: F401  (selects MuJoCo's headless backend before mujoco loads)
import pytest
import torch

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
pytest.importorskip("mujoco", reason="the sim extra is not installed (pip install -e '.[sim]')")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import camera_motion as cm


def test_homography_takes_the_corners_where_they_were_drawn():
    src = torch.tensor([[0.0, 0.0], [95.0, 0.0], [95.0, 95.0], [0.0, 95.0]], dtype=torch.float64)
    dst = src + torch.tensor([[3.0, -2.0], [-5.0, 1.0], [2.0, 4.0], [-1.0, -3.0]], dtype=torch.float64)
    H = cm.homography(src, dst)
    mapped = torch.cat([src, src.new_ones(4, 1)], 1) @ H.T
    torch.testing.assert_close(mapped[:, :2] / mapped[:, 2:], dst)


def test_motion_of_a_shift_and_of_a_turn_about_the_workspace_centre():
    before = torch.tensor([[10.0, 10.0], [50.0, 50.0], [90.0, 20.0]])
    shift, outside, angle = cm.motion(before, before + torch.tensor([9.6, 0.0]), 96)
    assert shift == pytest.approx(10.0) and outside == pytest.approx(100 / 3) and math.isnan(angle)
    eye = cm.CENTRE + torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    turned = cm.CENTRE + torch.tensor([0.0, 2.0, 0.0], dtype=torch.float64)  # 90 deg, another distance
    assert cm.motion(before, before, 96, (eye, turned))[2] == pytest.approx(90.0)
    assert cm.summary([(1.0, 0.0, math.nan), (3.0, 0.0, math.nan)])["view_change_deg_median"] is None


def test_a_small_run_orders_the_paper_levels():
    rows = cm.run(episodes=6, size=48)["rows"]
    assert set(rows) == {"paper/none", "paper/small", "paper/medium", "paper/large", "vista/small_perturb",
                         "vista/arc_90deg", "fov/zoom", "train/gensplat", "train/gensplat-wide",
                         "train/gensplat-fov", "train/gensplat-tilt", "train/gensplat-arc", "train/gensplat-tiltarc", "train/gensplat-zoom",
                         "train/gensplat-unmoved", "train/perspective"}  # fmt: skip
    # arcs change the viewpoint beyond the paper's moves; tilts turn the camera about its own centre
    assert rows["train/gensplat-arc"]["view_change_deg_p95"] > rows["train/gensplat"]["view_change_deg_p95"]
    assert rows["train/gensplat-tilt"]["view_change_deg_median"] < rows["train/gensplat"]["view_change_deg_median"]
    # a zoom moves the image points, not the camera
    assert rows["fov/zoom"]["shift_pct_median"] > 1.0 and rows["fov/zoom"]["view_change_deg_p95"] == 0.0
    assert rows["train/gensplat-zoom"]["shift_pct_median"] > 1.0 and rows["train/gensplat-zoom"]["view_change_deg_p95"] == 0.0
    assert rows["train/gensplat-unmoved"]["shift_pct_p95"] == rows["train/gensplat-unmoved"]["view_change_deg_p95"] == 0.0
    assert rows["train/gensplat-fov"]["shift_pct_median"] > rows["train/gensplat"]["shift_pct_median"]
    # the wide arm's tilts turn the camera about its own centre: they move the image more
    assert rows["train/gensplat-wide"]["shift_pct_p95"] > rows["train/gensplat"]["shift_pct_p95"]
    assert rows["paper/none"]["shift_pct_median"] == 0.0 and rows["paper/none"]["view_change_deg_median"] == 0.0
    shifts = [rows[f"paper/{lv}"]["shift_pct_median"] for lv in ("small", "medium", "large")]
    assert shifts == sorted(shifts) and shifts[0] > 0
    assert rows["train/perspective"]["view_change_deg_median"] is None and rows["train/gensplat-wide"]["moves"] == 18
