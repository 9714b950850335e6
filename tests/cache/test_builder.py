"""Where a rig of two cameras turns about: the crossing of their optical axes where it lies at
the scene, else a point on camera 0's axis at the scene's depth (nearly parallel, diverging or
crossing axes), chosen once by ``gensplat cache`` (``cache.builder.pivot_depth``)."""

import dataclasses
import json
import logging

import pytest
import torch

from gensplat_transforms.cache.builder import PIVOT_TOLERANCE, SceneEpisodes, pivot_depth, scene_depth
from gensplat_transforms.core.cameras import Cameras, look_at
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.data.scenes import DEFAULT_VIEWS, WORKSPACE_CENTER
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.settings import GenSplatConfig
from gensplat_transforms.views.perturbation import Perturbation, move_rig, rig_pivot

F64 = torch.float64


def episodes_seen_by(right_eye, right_target) -> SceneEpisodes:
    """The procedural episodes with the right camera at ``right_eye`` looking at ``right_target``."""
    source = SceneEpisodes(num_episodes=2, num_frames=2, size=24)
    c2w = source.cameras.c2w.clone()
    c2w[1] = look_at(right_eye, right_target)
    source.cameras = Cameras(source.cameras.K, c2w, source.cameras.width, source.cameras.height)
    return source


def beside_left(offset_y: float, toe_in_m: float = 0.0) -> SceneEpisodes:
    """The right camera ``offset_y`` metres beside the left one, looking the same way, its
    target moved ``toe_in_m`` towards the left camera's (a toe-in, or a toe-out when negative)."""
    eye, target = (torch.tensor(v, dtype=F64) for v in DEFAULT_VIEWS["left"])
    shift = torch.tensor([0.0, offset_y, 0.0], dtype=F64)
    return episodes_seen_by((eye + shift).tolist(), (target + shift * (1 - toe_in_m / abs(offset_y))).tolist())


def test_cameras_whose_axes_cross_at_the_scene_keep_their_crossing_as_the_pivot(caplog, capsys):
    source = SceneEpisodes(num_episodes=2, num_frames=2, size=24)
    with caplog.at_level(logging.WARNING):
        assert pivot_depth(RGBDReconstructor(), source, range(2), progress=True) is None
    assert not caplog.records
    assert "placing the pivot" in capsys.readouterr().err  # the sampled reconstructions' progress bar
    pivot = rig_pivot(source.cameras.c2w[:2])
    torch.testing.assert_close(pivot, torch.tensor(WORKSPACE_CENTER, dtype=pivot.dtype))


@pytest.mark.parametrize(("source", "why"), [
    (beside_left(-0.1), "parallel: the crossing falls back to the centres' midpoint, beside the lenses"),
    (beside_left(-0.1, toe_in_m=0.003), "nearly parallel: the axes cross tens of metres away"),
    (beside_left(-0.1, toe_in_m=-0.02), "diverging: the axes pass closest behind the cameras"),
    (episodes_seen_by((0.36, -0.60, 0.48), (0.28, 0.58, 0.5)), "crossing a few centimetres from the left lens"),
])  # fmt: skip
def test_a_pivot_far_from_the_scene_moves_onto_camera_0s_axis_at_its_depth_with_a_warning(source, why, caplog):
    c2w = source.cameras.c2w[:2]
    axis = c2w[0, :3, 2]
    ahead = float((rig_pivot(c2w) - c2w[0, :3, 3]) @ axis)
    depth = scene_depth(RGBDReconstructor(), source, range(2))
    assert not depth / PIVOT_TOLERANCE <= ahead <= depth * PIVOT_TOLERANCE, why  # the crossing is off the scene
    with caplog.at_level(logging.WARNING):
        assert pivot_depth(RGBDReconstructor(), source, range(2)) == depth
    assert "cameras 'left' and 'right': their optical axes pass closest" in caplog.text
    assert f"on 'left''s axis at the scene's depth (pivot_depth {depth:.3g})" in caplog.text


class Faint:
    """The RGB-D reconstruction with every Gaussian at opacity 0.1: no scene depth to be seen."""

    def reconstruct(self, views):
        rec = RGBDReconstructor().reconstruct(views)
        g = rec.gaussians
        return dataclasses.replace(rec, gaussians=Gaussians(g.means, g.quats, g.scales, torch.full_like(g.opacities, 0.1), g.sh))


def test_without_a_scene_depth_a_crossing_in_front_stands_and_one_elsewhere_is_an_error():
    assert pivot_depth(Faint(), SceneEpisodes(num_episodes=1, num_frames=2, size=16), [0]) is None
    with pytest.raises(ValueError, match=r"no reconstructed point in front of camera 'left' in 2 sampled timesteps"):
        pivot_depth(Faint(), beside_left(-0.1), range(1))


def test_a_pivot_depth_puts_the_pivot_of_any_rig_on_camera_0s_axis_in_both_paths():
    cameras = SceneEpisodes(size=24).cameras[:2]
    c2w = cameras.c2w
    pivot = rig_pivot(c2w, pivot_depth=0.5)
    torch.testing.assert_close(pivot, c2w[0, :3, 3] + 0.5 * c2w[0, :3, 2])
    move = Perturbation("x", 10.0, 0.02)
    for view in (0, 1):
        worker = move.move(cameras, view, pivot_depth=0.5).c2w[0]
        batch = move_rig(c2w, torch.tensor([move.as_row()], dtype=F64), [view], pivot_depth=0.5)[0]
        torch.testing.assert_close(worker, batch)
        assert torch.allclose(worker, move.apply(c2w[view], pivot))
    assert not torch.allclose(move.move(cameras, 1).c2w, move.move(cameras, 1, pivot_depth=0.5).c2w)
    assert GenSplatConfig(pivot_depth=0.5).pivot_depth == 0.5  # two cameras take one too
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match=r"^GenSplatConfig.pivot_depth: a positive distance in metres, at most 100, got"):
            GenSplatConfig(pivot_depth=bad)


def test_gensplat_cache_stores_the_pivot_on_camera_0s_axis_for_a_rig_whose_axes_do_not_cross(tmp_path, caplog, capsys):
    pytest.importorskip("lerobot", reason="the LeRobot commands need the lerobot extra")
    from gensplat_cli import main
    from gensplat_lerobot.scene_dataset import record_scene_dataset

    root, repo = tmp_path / "ds", "local/parallel_rig"
    source = beside_left(-0.1, toe_in_m=0.003)
    record_scene_dataset(root, source, repo, progress=False)
    with caplog.at_level(logging.WARNING):
        assert main(["cache", "--root", str(root), "--repo-id", repo]) == 0
    assert "their optical axes pass closest" in caplog.text
    stored = json.loads((root / "gensplat" / "config.json").read_text())["transform"]
    assert stored["cameras"] == ["left", "right"]
    assert stored["pivot_depth"] == pytest.approx(scene_depth(RGBDReconstructor(), source, range(2)), rel=0.05)
    caplog.clear()
    with caplog.at_level(logging.WARNING):  # a distance given is taken as it is, unchecked
        assert main(["cache", "--root", str(root), "--repo-id", repo, "--pivot-depth", "0.6"]) == 0
    assert "optical axes" not in caplog.text
    assert json.loads((root / "gensplat" / "config.json").read_text())["transform"]["pivot_depth"] == 0.6
    with pytest.raises(SystemExit):
        main(["cache", "--root", str(root), "--repo-id", repo, "--pivot-depth", "far"])
    capsys.readouterr()
    assert main(["cache", "--root", str(root), "--repo-id", repo, "--pivot-depth", "-1"]) == 2
    assert "GenSplatConfig.pivot_depth: a positive distance in metres, at most 100, got -1.0" in capsys.readouterr().err
