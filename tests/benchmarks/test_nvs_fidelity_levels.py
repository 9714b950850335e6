"""benchmarks/nvs_fidelity.py's levels: the paper's, or (``--samplers``) the moves the policy
study's wider arms train on and its field-of-view protocol."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gensplat_sim  # noqa: F401  (selects MuJoCo's headless backend before mujoco loads)
import pytest

from gensplat_transforms.views.perturbation import EVAL_LEVELS, ArcSampler, TiltSampler

pytest.importorskip("lerobot", reason="the LeRobot extra is not installed (pip install -e '.[lerobot]')")
pytest.importorskip("mujoco", reason="the sim extra is not installed (pip install -e '.[sim]')")
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
import nvs_fidelity as nf
import policy_robustness as pr


def test_the_paper_levels_by_default():
    samplers = nf.level_samplers(argparse.Namespace(samplers=False, seed=0))
    assert tuple(samplers) == EVAL_LEVELS
    assert samplers["large"].sample(0).theta_deg != 0 and samplers["none"].sample(0).theta_deg == 0


def test_samplers_draw_the_wider_arms_moves_and_the_fov_protocols_zoom():
    samplers = nf.level_samplers(argparse.Namespace(samplers=True, seed=0))
    assert list(samplers) == ["none", "tilt", "arc", "zoom"]
    tilt, arc = samplers["tilt"], samplers["arc"]
    assert isinstance(tilt, TiltSampler) and isinstance(arc, ArcSampler)
    assert (tilt.limit_deg, tilt.shift_m) == (pr.SAMPLER_ARMS["gensplat-tilt"]["tilt_deg"], 0.03)
    assert (arc.limit_deg, arc.shift_m) == (pr.SAMPLER_ARMS["gensplat-arc"]["arc_deg"], 0.03)
    zooms = [samplers["zoom"].sample(ep, view=d) for ep in range(20) for d in range(2)]
    assert all(z.theta_deg == 0 and z.mu_m == 0 and z.shift_m == (0.0, 0.0, 0.0) for z in zooms)  # the camera stays
    scales = [z.focal_scale for z in zooms]
    assert min(scales) < 0.95 and max(scales) > 1.05 and all(0.8 <= s <= 1.25 for s in scales)
    none = samplers["none"].sample(3)
    assert none.theta_deg == 0 and none.focal_scale == 1.0
