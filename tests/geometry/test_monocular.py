"""The monocular reconstructor: MoGe-2's metric depth per image, then the RGB-D discs; through
make_reconstructor and ``gensplat cache --reconstructor monocular`` on a checkpoint the test
writes (random weights: the numbers say nothing of quality, the plumbing is what is checked)."""

from __future__ import annotations

import math

import pytest
import torch
from tiny_moge import TINY, randomize

from gensplat_transforms.cache.builder import SceneEpisodes
from gensplat_transforms.geometry import MonocularReconstructor, Views, make_reconstructor
from gensplat_transforms.geometry.geometry import weights_licence
from gensplat_transforms.geometry.model.moge import MoGe2, MoGe2Config

TOKENS = 16
FAST = {**TINY, "num_tokens_range": [TOKENS, TOKENS]}  # the default grid of a fast test


@pytest.fixture(scope="module")
def moge() -> MoGe2:
    return randomize(MoGe2(MoGe2Config.from_dict(FAST))).eval()


@pytest.fixture(scope="module")
def views() -> Views:
    return SceneEpisodes(num_episodes=1, num_frames=1, size=28).views(0, 0)


def test_calibrated_views_keep_their_cameras_and_give_moges_metric_depth(moge, views, monkeypatch):
    asked = {}
    infer = moge.infer

    def spy(images, **kwargs):
        asked.update(kwargs)
        return infer(images, **kwargs)

    monkeypatch.setattr(moge, "infer", spy)
    rec = MonocularReconstructor(moge)
    out = rec.predict_depth(views)
    assert out.depths.shape == (2, 1, 28, 28) and out.depths.dtype == torch.float32
    assert torch.isfinite(out.depths).all() and (out.depths >= 0).all() and (out.depths > 0).any()
    assert torch.equal(out.cameras.K, views.cameras.K) and torch.equal(out.cameras.c2w, views.cameras.c2w)
    fx = views.cameras.K[:, 0, 0]
    torch.testing.assert_close(asked["fov_x"].double(), torch.rad2deg(2 * torch.atan(28 / (2 * fx))), rtol=1e-6, atol=0)
    assert asked["num_tokens"] == TOKENS  # the checkpoint's default grid
    expected = moge.infer(views.images, num_tokens=TOKENS, fov_x=asked["fov_x"])["depth"]
    assert torch.equal(out.depths[:, 0], expected)
    g = rec.reconstruct(views).gaussians
    assert len(g) == int((out.depths > 0).sum()) and torch.isfinite(g.means).all()


def test_one_uncalibrated_view_gets_moges_camera_and_several_are_refused(moge, views, monkeypatch):
    rec = MonocularReconstructor(moge, num_tokens=TOKENS)
    with pytest.raises(ValueError, match=r"MoGe-2 gave no usable camera for this image \(fx = -"):
        rec.predict_depth(Views(views.images[:1]))  # random weights: a focal length below zero
    infer = moge.infer

    def at_60_degrees(images, **kwargs):  # a model that found a 60 deg field of view
        return infer(images, **{**kwargs, "fov_x": 60.0})

    monkeypatch.setattr(moge, "infer", at_60_degrees)
    one = rec.predict_depth(Views(views.images[:1]))
    K = one.cameras.K[0]
    assert (one.cameras.width, one.cameras.height) == (28, 28)
    assert float(K[0, 2]) == float(K[1, 2]) == 14.0 and float(K[0, 0]) > 0
    assert torch.equal(one.cameras.c2w[0], torch.eye(4, dtype=torch.float64))
    assert math.degrees(2 * math.atan(14 / float(K[0, 0]))) == pytest.approx(60.0, abs=1e-3)
    with pytest.raises(ValueError, match="2 uncalibrated views; a single-image model gives no relative pose"):
        rec.predict_depth(Views(views.images))


def test_a_checkpoint_folder_through_make_reconstructor(moge, tmp_path):
    folder = moge.save_pretrained(tmp_path / "moge")
    rec = make_reconstructor({"name": "monocular", "model": str(folder), "options": {"num_tokens": 8}})
    assert isinstance(rec, MonocularReconstructor) and rec.num_tokens == 8
    assert rec.identity() == MonocularReconstructor(moge, num_tokens=8).identity()
    assert rec.identity() != MonocularReconstructor(moge, num_tokens=16).identity()
    assert weights_licence(folder) == "MIT (MoGe-2)"
    with pytest.raises(ValueError, match="the monocular reconstructor needs model: a MoGe-2 checkpoint folder"):
        make_reconstructor({"name": "monocular"})
    with pytest.raises(ValueError, match="num_tokens must be a positive integer"):
        MonocularReconstructor(moge, num_tokens=0)
    with pytest.raises(FileNotFoundError, match="no such directory"):
        MonocularReconstructor(tmp_path / "missing")


def test_gensplat_cache_builds_a_depth_cache_with_it_and_refuses_it_without_a_model(moge, scene_dataset, dataset_copy,
                                                                                     tmp_path, capsys):
    pytest.importorskip("lerobot", reason="gensplat cache reads LeRobot datasets (the lerobot extra)")
    from gensplat_cli import main

    repo = "local/monocular"
    root = dataset_copy(scene_dataset(repo, episodes=1, frames=3, size=28))
    assert main(["cache", "--root", str(root), "--repo-id", repo, "--reconstructor", "monocular"]) == 2
    assert "gensplat: error: --reconstructor monocular needs --model <MoGe-2 checkpoint folder>" in \
        capsys.readouterr().err
    assert not (root / "gensplat").exists()  # refused before anything was written
    truncated = tmp_path / "truncated"
    truncated.mkdir()
    (truncated / "model.pt").write_bytes(b"PK\x03\x04 cut short")
    for model, message in ((tmp_path / "missing", "no such directory"), (truncated, "not a readable torch checkpoint")):
        capsys.readouterr()
        assert main(["cache", "--root", str(root), "--repo-id", repo, "--reconstructor", "monocular", "--model",
                     str(model)]) == 2  # fmt: skip
        err = capsys.readouterr().err
        assert err.startswith("gensplat: error: ") and message in err and "Traceback" not in err
    folder = moge.save_pretrained(tmp_path / "moge")
    main(["cache", "--root", str(root), "--repo-id", repo, "--reconstructor", "monocular", "--model", str(folder)])
    caches = list((root / "gensplat" / "cache").iterdir())
    assert len(caches) == 1 and any(caches[0].glob("*episode*"))
    out = capsys.readouterr().out
    assert "path: MoGe-2's metric depth of each image, then RGB-D discs;" in out and "ms per timestep built" in out
    assert "licence MIT (MoGe-2)" in out


def test_the_frames_of_a_run_are_aligned_in_scale_to_its_first_frames(moge, views, monkeypatch):
    """Frame k of a run predicted at (1 + 0.1 k) times one depth: the run's frames come out at one
    scale (the median of its first frames'), beyond the first ALIGN_FRAMES too; one timestep alone
    keeps its own; a camera with almost no depth is left as predicted."""
    from gensplat_transforms.geometry import monocular

    base = torch.linspace(0.5, 1.5, 28 * 28).reshape(28, 28)
    calls = []

    def wavering(images, **kwargs):
        k = len(calls)
        calls.append(k)
        depth = base.expand(len(images), 28, 28) * (1 + 0.1 * k)
        depth = torch.where(torch.arange(len(images))[:, None, None] == 1, depth * (base > 1.49), depth)  # view 1: sparse
        return {"depth": depth, "mask": depth > 0, "intrinsics": None}

    monkeypatch.setattr(moge, "infer", wavering)
    rec = MonocularReconstructor(moge)
    frames = list(rec.predict_depths(views for _ in range(monocular.ALIGN_FRAMES + 4)))
    assert len(frames) == monocular.ALIGN_FRAMES + 4
    median = 1 + 0.1 * 7  # of the first 16 frames' factors 1.0 .. 2.5 (torch: the lower middle one)
    for f in frames:
        torch.testing.assert_close(f.depths[0, 0], base * median)
    assert not torch.equal(frames[0].depths[1], frames[-1].depths[1])  # too little depth to align: as predicted
    alone = rec.predict_depth(views).depths[0, 0]
    torch.testing.assert_close(alone, base * (1 + 0.1 * len(calls[:-1])))  # its own scale
