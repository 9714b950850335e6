"""Simulated RGB-D sensor depth: noise ~ z^2, holes at edges and on dark surfaces, 1 mm
steps, colour-depth misregistration, determinism, and the recording hook (off by default)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest
import torch
from gensplat_sim.sensor import SensorDepthConfig, sensor_depth

SIZE = 96
F = 100.0
K = torch.tensor([[F, 0.0, SIZE / 2], [0.0, F, SIZE / 2], [0.0, 0.0, 1.0]])
GREY = torch.full((3, SIZE, SIZE), 0.5)
EXACT = SensorDepthConfig(
    subpixel=0.0, quantum=0.0, occlusion=False, edge_px=0, dark_dropout=0.0, shift_px=(0, 0)
)


D435 = SensorDepthConfig()


def run(depth, config=D435, rgb=GREY, seed=0):
    return sensor_depth(depth, rgb, K, config, torch.Generator().manual_seed(seed))


def plane(z: float) -> torch.Tensor:
    return torch.full((SIZE, SIZE), z)


def box(near=0.6, far=1.0, lo=32, hi=64) -> torch.Tensor:
    """A fronto-parallel square at ``near`` in front of a wall at ``far``."""
    z = plane(far)
    z[lo:hi, lo:hi] = near
    return z


def test_recording_is_exact_unless_asked_and_an_all_off_sensor_is_exact():
    from gensplat_sim.record import RecordConfig

    assert RecordConfig(Path("unused")).sensor_depth is None
    z = box() + torch.linspace(0, 0.01, SIZE)
    assert torch.equal(run(z, EXACT), z)


def test_noise_std_grows_with_the_square_of_the_distance():
    config = replace(D435, shift_px=(0, 0))
    std = {}
    for z in (1.0, 2.0):
        out = run(plane(z), config)
        assert (out > 0).all()  # no edges, no dark pixels: every pixel measured
        std[z] = float((out - z).std())
        assert std[z] == pytest.approx(float(config.noise_std(torch.tensor(z))), rel=0.05)
    assert std[2.0] / std[1.0] == pytest.approx(4.0, rel=0.05)
    assert std[1.0] == pytest.approx(0.08 / (424 * 0.05), rel=0.05)  # 3.8 mm at 1 m (D435)


def test_holes_at_depth_edges_and_in_the_occlusion_shadow():
    config = replace(EXACT, occlusion=True, edge_px=1)
    out = run(box(), config)
    rows = slice(34, 62)  # away from the square's top and bottom edges
    assert (out[rows, 33:63] == 0.6).all() and (out[rows, 65:] == 1.0).all()
    assert (out[rows, 31:33] == 0).all() and (out[rows, 64] == 0).all()  # 1 px each side
    # The second imager (5 cm to the right) cannot see the wall just left of the square:
    # F * baseline * (1 / 0.6 - 1 / 1.0) = 3.3 px wide.
    assert (out[rows, 29:31] == 0).all() and (out[rows, :29] == 1.0).all()
    no_shadow = run(box(), replace(config, occlusion=False))
    assert (no_shadow[rows, :31] == 1.0).all()
    assert (run(box(), replace(config, edge_px=2))[rows, 30:34] == 0).all()


def test_dark_surfaces_drop_out_with_the_given_probability():
    rgb = GREY.clone()
    rgb[:, :, : SIZE // 2] = 0.05
    config = replace(EXACT, dark_dropout=0.5)
    out = run(plane(1.0), config, rgb)
    assert float((out[:, : SIZE // 2] == 0).float().mean()) == pytest.approx(0.5, abs=0.04)
    assert (out[:, SIZE // 2 :] == 1.0).all()
    assert (run(plane(1.0), replace(config, dark_dropout=1.0), rgb)[:, : SIZE // 2] == 0).all()


def test_depth_is_quantised_to_the_step():
    z = 0.5 + torch.rand(SIZE, SIZE, generator=torch.Generator().manual_seed(1))
    for quantum in (0.001, 0.005):
        out = run(z, replace(EXACT, quantum=quantum)).double() / quantum
        assert (out - out.round()).abs().max() < 1e-3
        assert (out * quantum - z).abs().max() <= quantum / 2 + 1e-6
    noisy = run(plane(1.0), replace(D435, shift_px=(0, 0)))
    steps = torch.unique(noisy).diff()
    assert steps.min() == pytest.approx(0.001, abs=1e-5)


def test_misregistration_shifts_depth_against_colour():
    z = 1.0 + 0.001 * torch.arange(SIZE * SIZE, dtype=torch.float32).reshape(SIZE, SIZE) / SIZE
    out = run(z, replace(EXACT, shift_px=(2, -1)))  # 2 px right, 1 px up
    assert torch.equal(out[: SIZE - 1, 2:], z[1:, : SIZE - 2])
    assert (out[:, :2] == 0).all() and (out[SIZE - 1] == 0).all()
    assert torch.equal(run(z, replace(EXACT, shift_px=(1, 0)))[:, 1:], z[:, :-1])


def test_same_seed_same_depth_other_seed_other_noise():
    rgb = torch.rand(3, SIZE, SIZE, generator=torch.Generator().manual_seed(2))
    a, b, c = run(box(), rgb=rgb, seed=7), run(box(), rgb=rgb, seed=7), run(box(), rgb=rgb, seed=8)
    assert torch.equal(a, b) and not torch.equal(a, c)


def test_never_nan_inf_or_negative():
    z = torch.linspace(-5, 50, SIZE * SIZE).reshape(SIZE, SIZE)
    z[0, :6] = torch.tensor([float("nan"), float("inf"), -float("inf"), 0.0, 1e30, 1e-9])
    rgb = torch.rand(3, SIZE, SIZE, generator=torch.Generator().manual_seed(3))
    for config in (D435, replace(D435, subpixel=50.0, depth_range=(0.0, 1e38))):
        out = run(z, config, rgb)
        assert out.dtype == torch.float32 and torch.isfinite(out).all() and (out >= 0).all()
        assert (out[0, :6] == 0).all()
    assert (run(z, rgb=rgb)[:, 1:][z[:, :-1] > 10.0] == 0).all()  # beyond the D435's range


@pytest.mark.timeout(300)
def test_recording_with_sensor_depth(tmp_path):
    pytest.importorskip("mujoco", reason="the simulated world needs the 'sim' extra")
    from gensplat_sim.record import RecordConfig, record
    from gensplat_sim.truth import GroundTruth
    from gensplat_sim.world import WorldConfig

    from gensplat_transforms.data.format import load_depth

    root = tmp_path / "sensor"
    config = D435
    record(RecordConfig(root, episodes=1, seed=3, use_videos=False, world=WorldConfig(height=64, width=64),
                        sensor_depth=config), progress=False)  # fmt: skip
    assert json.loads((root / "sim" / "world.json").read_text())["sensor_depth"]["quantum"] == config.quantum
    depth = load_depth(root, "left", 0)
    truth = GroundTruth(root)
    _, exact = truth.render(0, 0, truth.cameras(0, 0, ("left",)))
    truth.close()
    measured, exact = depth[0, 0, :, 1:], exact[0, 0, :, :-1]  # depth is 1 px right of colour
    holes = measured == 0
    assert 0.01 < float(holes.float().mean()) < 0.3 and (depth[0, 0, :, 0] == 0).all()
    err = (measured - exact)[~holes]
    assert 0 < float(err.abs().median()) and float((err.abs() / exact[~holes] ** 2).max()) < 0.05
