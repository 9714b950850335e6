"""The feed-forward GenSplat model: Pi3 compatibility, equivariance, checkpoints, reconstructor."""

import json
import math
import sys
from pathlib import Path

import pytest
import torch
from safetensors.torch import save_file
from tiny_model import tiny_model as perturbed_model

from gensplat_transforms.core.cameras import Cameras, look_at
from gensplat_transforms.core.rotations import quat_to_rotmat
from gensplat_transforms.core.sh import sh_basis
from gensplat_transforms.geometry import GenSplatReconstructor, Views
from gensplat_transforms.geometry.model import GenSplatModel, ModelConfig, load_pi3_weights, to_gaussians
from gensplat_transforms.geometry.model.frames import (
    align_similarity,
    estimate_focal,
    quat_mul,
    sh_rotation,
    transform_poses,
)
from gensplat_transforms.geometry.model.heads import svd_orthogonalize
from gensplat_transforms.geometry.model.layers import rope_2d

MANIFEST = Path(__file__).resolve().parents[3].parent / "shared" / "pi3_state_dict_manifest.json"
TINY = ModelConfig(
    dim=32, enc_depth=2, enc_heads=2, enc_pos_grid=4, dec_depth=4, dec_heads=2, head_dim=32, head_depth=1,
    head_heads=2, head_out_dim=32, camera_dim=32, gs_taps=(0, 1, 2, 3), gs_features=16, gs_rgb_features=8,
    sh_degree=2,
)  # fmt: skip
KEYS = ("camera_poses", "local_points", "points", "conf", "opacity", "quats", "scales", "sh")


def tiny_model(seed: int = 0) -> GenSplatModel:
    """The tiny model of this file's configuration (SH degree 2), every parameter perturbed."""
    return perturbed_model(seed, TINY)


def images(b=1, v=3, h=42, w=56, seed=1) -> torch.Tensor:
    return torch.rand(b, v, 3, h, w, generator=torch.Generator().manual_seed(seed))


@pytest.fixture(scope="module")
def model() -> GenSplatModel:
    return tiny_model()


# ---------------------------------------------------------------- forward
def test_outputs_have_documented_shapes_and_ranges(model):
    x = images(b=2, v=3)
    with torch.no_grad():
        out = model(x)
    B, V, H, W, K = 2, 3, 42, 56, 9
    shapes = {
        "camera_poses": (B, V, 4, 4), "local_points": (B, V, H, W, 3), "points": (B, V, H, W, 3),
        "conf": (B, V, H, W), "opacity": (B, V, H, W), "quats": (B, V, H, W, 4), "scales": (B, V, H, W, 3),
        "sh": (B, V, H, W, K, 3),
    }  # fmt: skip
    for k, shape in shapes.items():
        assert tuple(out[k].shape) == shape, k
        assert torch.isfinite(out[k]).all(), k
    poses = out["camera_poses"]
    R, t = poses[..., :3, :3], poses[..., :3, 3]
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.det(R), torch.ones(B, V), atol=1e-5, rtol=0)
    torch.testing.assert_close(poses[..., 3, :], torch.tensor([0.0, 0, 0, 1]).expand(B, V, 4))
    assert (out["local_points"][..., 2] > 0).all()
    world = torch.einsum("bvij,bvhwj->bvhwi", R, out["local_points"]) + t[:, :, None, None]
    torch.testing.assert_close(out["points"], world, atol=1e-5, rtol=1e-5)
    assert ((out["opacity"] > 0) & (out["opacity"] < 1)).all()
    torch.testing.assert_close(out["quats"].norm(dim=-1), torch.ones(B, V, H, W), atol=1e-5, rtol=0)
    assert (out["scales"] >= 0).all() and (out["scales"] <= 0.3).all()


def test_permuting_views_permutes_every_output(model):
    """Pi3 has no reference view: poses are in a frame chosen from the set of views, so even the
    camera poses (not only per-view quantities) are equivariant."""
    x = images(v=4, h=28, w=42)
    perm = torch.tensor([2, 0, 3, 1])
    with torch.no_grad():
        a, b = model(x), model(x[:, perm])
    for k in KEYS:
        torch.testing.assert_close(b[k], a[k][:, perm], atol=2e-4, rtol=1e-4, msg=k)


def test_views_see_each_other(model):
    """Global attention is live: changing one view changes another view's prediction (so the
    equivariance test above is not trivially passed by independent views)."""
    x = images(v=2)
    y = x.clone()
    y[:, 1] = 1 - y[:, 1]
    with torch.no_grad():
        a, b = model(x), model(y)
    for k in ("camera_poses", "local_points", "conf"):
        assert (a[k][:, 0] - b[k][:, 0]).abs().max() > 1e-4, k


@pytest.mark.parametrize(
    "shape",
    [(1, 3, 42, 42), (1, 2, 4, 42, 42), (1, 2, 3, 42, 40), (1, 2, 3, 30, 42), (1, 0, 3, 42, 42)],
)
def test_bad_image_shapes_raise(model, shape):
    with pytest.raises(ValueError, match="GenSplatModel"):
        model(torch.rand(shape))


def test_integer_images_raise(model):
    with pytest.raises(ValueError, match="float"):
        model(torch.zeros(1, 1, 3, 28, 28, dtype=torch.uint8))


def test_bf16_autocast_forward_has_no_nan(model):
    with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16):
        out = model(images(v=2))
    for k in KEYS:
        assert out[k].dtype == torch.float32, k  # the heads run in float32
        assert torch.isfinite(out[k]).all(), k


def test_gradient_checkpointing_gives_the_same_gradients():
    grads = []
    for ckpt in (False, True):
        m = tiny_model().train()
        m.set_gradient_checkpointing(ckpt)
        out = m(images(v=2, h=28, w=28))
        sum(out[k].sin().mean() for k in KEYS).backward()
        assert all(p.grad is not None for p in m.parameters())
        grads.append(torch.cat([p.grad.reshape(-1) for p in m.parameters()]))
    torch.testing.assert_close(grads[0], grads[1], atol=1e-6, rtol=1e-5)


def test_to_gaussians_one_per_pixel_and_confidence_mask(model):
    with torch.no_grad():
        out = model(images(b=2, v=2, h=28, w=28))
    g = to_gaussians(out, index=1)
    assert len(g) == 2 * 28 * 28 and g.sh_degree == 2
    torch.testing.assert_close(g.means, out["points"][1].reshape(-1, 3))
    thr = torch.sigmoid(out["conf"][1]).median().item()
    kept = to_gaussians(out, index=1, min_conf=thr)
    assert len(kept) == int((torch.sigmoid(out["conf"][1]) >= thr).sum())


@pytest.mark.parametrize(
    "change, message",
    [({"dim": 30}, "divisible"), ({"dec_depth": 3}, "even"), ({"gs_taps": (0, 1, 2)}, "gs_taps"),
     ({"sh_degree": 5}, "sh_degree"), ({"head_depth": 0}, "positive")],
)  # fmt: skip
def test_invalid_configs_raise(change, message):
    with pytest.raises(ValueError, match=message):
        ModelConfig(**{**TINY.to_dict(), **change})


# ---------------------------------------------------------------- Pi3 compatibility
def test_full_size_state_dict_matches_pi3_manifest():
    if not MANIFEST.is_file():
        pytest.skip(f"Pi3 manifest not found at {MANIFEST}")
    manifest = json.loads(MANIFEST.read_text())
    expected = {e["name"]: tuple(e["shape"]) for e in manifest["keys"]}
    with torch.device("meta"):
        model = GenSplatModel(ModelConfig.full())
    state = {k: tuple(v.shape) for k, v in model.state_dict().items()}
    assert [k for k in expected if k not in state] == []
    assert {k: (state[k], s) for k, s in expected.items() if state[k] != s} == {}
    extra = [k for k in state if k not in expected]
    assert extra and all(k.startswith("gaussian_head.") for k in extra)
    assert len(expected) == manifest["num_keys"] == 1210
    assert sum(math.prod(state[k]) for k in expected) == manifest["param_count"] == 958_696_738
    assert {"image_mean", "image_std"} <= set(state)  # persistent buffers, as in Pi3


def test_load_pi3_weights_reports_missing_and_unexpected(tmp_path):
    source = tiny_model(seed=3)
    pi3_like = {k: v for k, v in source.state_dict().items() if not k.startswith("gaussian_head.")}
    pi3_like["encoder.mask_token"] = torch.zeros(1, TINY.dim)
    save_file(pi3_like, str(tmp_path / "model.safetensors"))
    target = tiny_model(seed=4)
    report = load_pi3_weights(target, tmp_path / "model.safetensors")
    assert report.unexpected == ["encoder.mask_token"]
    assert report.missing and report.missing_outside_gaussian_head == []
    assert report.loaded == len(pi3_like) - 1
    for k, v in source.state_dict().items():
        if not k.startswith("gaussian_head."):
            assert torch.equal(target.state_dict()[k], v), k
    assert "Gaussian-head" in str(report)


def test_load_pi3_weights_rejects_another_size(tmp_path):
    save_file({k: v for k, v in tiny_model().state_dict().items()}, str(tmp_path / "model.safetensors"))
    other = GenSplatModel(ModelConfig(**{**TINY.to_dict(), "dim": 48, "enc_heads": 3, "dec_heads": 3}))
    with pytest.raises(ValueError, match="shape mismatch"):
        load_pi3_weights(other, tmp_path)


def test_from_pretrained_reads_a_pi3_directory(tmp_path, monkeypatch):
    """A Pi3 hub snapshot (its own config.json) builds the full size; the size is swapped for the
    tiny one here so the test stays small."""
    monkeypatch.setattr(ModelConfig, "full", classmethod(lambda cls: TINY))
    source = tiny_model(seed=5)
    state = {k: v for k, v in source.state_dict().items() if not k.startswith("gaussian_head.")}
    save_file(state, str(tmp_path / "model.safetensors"))
    (tmp_path / "config.json").write_text(json.dumps({"pos_type": "rope100", "decoder_size": "large"}))
    with pytest.warns(UserWarning, match="Pi3 checkpoint"):
        model = GenSplatModel.from_pretrained(tmp_path)
    assert torch.equal(model.decoder[1].attn.q_norm.weight, source.decoder[1].attn.q_norm.weight)


# ---------------------------------------------------------------- checkpoints
def test_save_and_load_round_trip_gives_identical_outputs(model, tmp_path):
    model.save_pretrained(tmp_path / "ckpt")
    meta = json.loads((tmp_path / "ckpt" / "config.json").read_text())
    assert meta["format"] == "gensplat-model" and meta["config"]["dim"] == TINY.dim
    loaded = GenSplatModel.from_pretrained(tmp_path / "ckpt")
    assert loaded.config == TINY and not loaded.training
    x = images(v=2)
    with torch.no_grad():
        a, b = model(x), loaded(x)
    for k in KEYS:
        assert torch.equal(a[k], b[k]), k


def test_hub_id_needs_huggingface_hub(monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "huggingface_hub", None)  # import fails; nothing is downloaded
    with pytest.raises(ImportError, match="huggingface_hub"):
        GenSplatModel.from_pretrained("someone/some-model")
    with pytest.raises(FileNotFoundError, match="no such directory"):
        GenSplatModel.from_pretrained("not/a/hub/id")


# ---------------------------------------------------------------- pieces
def test_svd_orthogonalize_keeps_rotations_and_never_reflects():
    R = quat_to_rotmat(torch.randn(8, 4))
    torch.testing.assert_close(svd_orthogonalize(R.reshape(8, 9)), R, atol=1e-5, rtol=0)
    out = svd_orthogonalize(torch.randn(64, 9))
    torch.testing.assert_close(torch.det(out), torch.ones(64), atol=1e-5, rtol=0)


def test_rope_depends_only_on_relative_position():
    q, k = torch.randn(1, 1, 1, 16), torch.randn(1, 1, 1, 16)

    def score(pq, pk):
        return (rope_2d(q, torch.tensor([[pq]]), 100.0) * rope_2d(k, torch.tensor([[pk]]), 100.0)).sum()

    torch.testing.assert_close(score((3, 5), (1, 2)), score((7, 9), (5, 6)), atol=1e-5, rtol=1e-5)
    assert (score((3, 5), (1, 2)) - score((3, 5), (2, 2))).abs() > 1e-4


def test_sh_rotation_moves_colour_with_the_frame():
    torch.manual_seed(0)
    R = quat_to_rotmat(torch.randn(4))
    c = torch.randn(5, 16, 3)  # degree 3
    d = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    new = sh_rotation(R, 16) @ c
    colour_new = torch.einsum("nk,nkc->nc", sh_basis(3, d), new)
    colour_old = torch.einsum("nk,nkc->nc", sh_basis(3, d @ R), c)  # d @ R = R^T d
    torch.testing.assert_close(colour_new, colour_old, atol=1e-4, rtol=1e-4)


def test_quat_mul_composes_rotations():
    a, b = torch.randn(6, 4), torch.randn(6, 4)
    a, b = a / a.norm(dim=-1, keepdim=True), b / b.norm(dim=-1, keepdim=True)
    torch.testing.assert_close(
        quat_to_rotmat(quat_mul(a, b)), quat_to_rotmat(a) @ quat_to_rotmat(b), atol=1e-5, rtol=0
    )


def test_estimate_focal_recovers_the_pinhole():
    H, W, f = 28, 42, 37.5
    v, u = torch.meshgrid(torch.arange(H) + 0.5 - H / 2, torch.arange(W) + 0.5 - W / 2, indexing="ij")
    z = 1 + torch.rand(H, W)
    pts = torch.stack([u / f * z, v / f * z, z], dim=-1)[None]
    torch.testing.assert_close(estimate_focal(pts), torch.tensor([f]), atol=1e-3, rtol=0)


def test_align_similarity_recovers_a_known_transform():
    src = torch.stack(
        [look_at(e, (0, 0, 0), dtype=torch.float32) for e in ((1, 0, 1), (0, 1, 1), (-1, 0, 1))]
    )
    R = quat_to_rotmat(torch.tensor([0.9, 0.1, -0.3, 0.2]))
    tgt = transform_poses(src, torch.tensor(2.5), R, torch.tensor([0.1, -0.2, 0.3]))
    scale, R_est, t_est = align_similarity(src, tgt)
    torch.testing.assert_close(scale, torch.tensor(2.5), atol=1e-5, rtol=0)
    torch.testing.assert_close(R_est, R, atol=1e-5, rtol=0)
    torch.testing.assert_close(transform_poses(src, scale, R_est, t_est), tgt, atol=1e-5, rtol=0)


# ---------------------------------------------------------------- reconstructor
def test_reconstructor_uncalibrated_uses_the_first_view_frame(model):
    rec = GenSplatReconstructor(model)
    views = Views(images(v=2, h=40, w=50)[0])  # not multiples of 14: resized to 42 x 56 inside
    out = rec.reconstruct(views)
    assert (out.cameras.width, out.cameras.height) == (50, 40) and len(out.cameras) == 2
    torch.testing.assert_close(out.cameras.c2w[0], torch.eye(4), atol=1e-5, rtol=0)
    assert len(out.gaussians) == 2 * 42 * 56
    assert (out.cameras.K[:, 0, 0] > 0).all()


def test_reconstructor_calibrated_lands_in_the_dataset_frame(model):
    c2w = torch.stack([look_at(e, (0, 0, 0), dtype=torch.float32) for e in ((1, 0, 1), (0, 1, 1))])
    cams = Cameras.from_intrinsics(30.0, 30.0, 21.0, 21.0, c2w, 42, 42)
    out = GenSplatReconstructor(model, min_conf=0.0, placement="similarity").reconstruct(
        Views(images(v=2, h=42, w=42)[0], cams)
    )
    # two cameras: the aligned centres reproduce the given baseline and midpoint exactly
    centers = out.cameras.c2w[:, :3, 3]
    torch.testing.assert_close((centers[0] - centers[1]).norm(), (c2w[0, :3, 3] - c2w[1, :3, 3]).norm())
    torch.testing.assert_close(centers.mean(0), c2w[:, :3, 3].mean(0), atol=1e-4, rtol=0)


@pytest.mark.parametrize("metric", [True, False])
def test_reconstructor_per_view_placement_uses_the_calibrated_rays(model, metric):
    c2w = torch.stack([look_at(e, (0, 0, 0), dtype=torch.float32) for e in ((1, 0, 1), (0, 1, 1))])
    cams = Cameras.from_intrinsics(30.0, 30.0, 21.0, 21.0, c2w, 42, 42)
    views = Views(images(v=2, h=42, w=42)[0], cams)
    out = GenSplatReconstructor(model, metric=metric).reconstruct(views)
    assert out.cameras is cams  # the given cameras reproduce the source views
    with torch.no_grad():
        pred = model(views.images[None])
    scale = 1.0 if metric else align_similarity(pred["camera_poses"][0], c2w)[0]
    depth = scale * pred["local_points"][0, ..., 2].reshape(2, -1)
    v, u = torch.meshgrid(torch.arange(42) + 0.5, torch.arange(42) + 0.5, indexing="ij")
    centres = torch.stack([u, v], -1).reshape(1, -1, 2).expand(2, -1, -1)
    means = out.gaussians.means.reshape(2, -1, 3)
    # each Gaussian lies on its pixel's calibrated ray, at the (scaled) predicted depth
    torch.testing.assert_close(means, cams.unproject(centres, depth), atol=1e-5, rtol=1e-5)


def test_reconstructor_rejects_unknown_placement(model):
    with pytest.raises(ValueError, match="placement must be one of"):
        GenSplatReconstructor(model, placement="nearest")


def test_reconstructor_identity_tracks_the_weights():
    a = GenSplatReconstructor(tiny_model(seed=0))
    b = GenSplatReconstructor(tiny_model(seed=0))
    c = GenSplatReconstructor(tiny_model(seed=1))
    assert a.identity() == b.identity() != c.identity()
    assert len(a.config()["weights"]) == 16


def test_a_foreign_checkpoint_is_refused_from_its_header_before_the_model_is_built(tmp_path, monkeypatch):
    """Four tensors of another architecture under a Pi3-like config: refused naming what is
    missing, before the (here: tiny) full-size model is allocated; a config that is a JSON list
    is a clear error too."""
    monkeypatch.setattr(ModelConfig, "full", classmethod(lambda cls: TINY))
    save_file({f"other.layer{i}.weight": torch.zeros(3, 3) for i in range(4)}, str(tmp_path / "model.safetensors"))
    (tmp_path / "config.json").write_text(json.dumps({"pos_type": "rope100", "decoder_size": "large"}))
    built = []
    real_init = GenSplatModel.__init__
    monkeypatch.setattr(GenSplatModel, "__init__", lambda self, *a, **k: built.append(torch.empty(0).device.type)
                        or real_init(self, *a, **k))  # fmt: skip
    with pytest.raises(ValueError, match=r"model.safetensors: not a Pi3 checkpoint of this model .* tensors are missing"):
        GenSplatModel.from_pretrained(tmp_path)
    assert built == ["meta"]  # only the shapes were built, on the meta device
    (tmp_path / "config.json").write_text("[1, 2]")
    from gensplat_transforms.geometry.geometry import GeometryReconstructor, is_gensplat_checkpoint

    with pytest.raises(ValueError, match=r"config.json: expected a JSON object, got list"):
        is_gensplat_checkpoint(tmp_path)
    with pytest.raises(ValueError, match=r"config.json: expected a JSON object, got list"):
        GeometryReconstructor(tmp_path)


@pytest.mark.parametrize("config", ["missing", "a folder"])
def test_a_checkpoint_folder_without_a_config_file_is_a_clear_error(tmp_path, config):
    """``gensplat cache --reconstructor geometry --model DIR`` of an empty folder was a raw
    FileNotFoundError traceback from pathlib (IsADirectoryError for a folder named config.json)."""
    from gensplat_transforms.geometry.geometry import GeometryReconstructor

    if config == "a folder":
        (tmp_path / "config.json").mkdir()
    with pytest.raises(FileNotFoundError, match=r"config.json: no such file \(a checkpoint folder holds config.json"):
        GeometryReconstructor(tmp_path)
