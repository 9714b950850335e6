"""Depth Anything 3 (DA3-Small / DA3-Base, Apache-2.0 weights): key layout, loading, forward.

The expected keys and shapes below were read off the module structure of
ByteDance-Seed/Depth-Anything-3 (``DepthAnything3Net`` built from ``configs/da3-small.yaml``
and ``da3-base.yaml``, behind the ``model.`` attribute of its hub wrapper). No real weights
are used here: every checkpoint is written by the test.
"""

from __future__ import annotations

import json
import math
import re

import pytest
import torch
from safetensors.torch import load_file, save_file, save_model

from gensplat_transforms.geometry.model.da3 import (
    TIED,
    DA3Config,
    DepthAnything3,
    pose_encoding_to_cameras,
    unproject,
)

#: a subset of the published DA3-Small state dict: first and last keys of each block
SMALL_KEYS = {
    "model.backbone.pretrained.cls_token": (1, 1, 384),
    "model.backbone.pretrained.camera_token": (1, 2, 384),
    "model.backbone.pretrained.pos_embed": (1, 1370, 384),
    "model.backbone.pretrained.patch_embed.proj.weight": (384, 3, 14, 14),
    "model.backbone.pretrained.blocks.0.norm1.weight": (384,),
    "model.backbone.pretrained.blocks.3.attn.qkv.weight": (1152, 384),
    "model.backbone.pretrained.blocks.4.attn.q_norm.weight": (64,),
    "model.backbone.pretrained.blocks.4.attn.k_norm.bias": (64,),
    "model.backbone.pretrained.blocks.11.mlp.fc1.weight": (1536, 384),
    "model.backbone.pretrained.blocks.11.ls2.gamma": (384,),
    "model.backbone.pretrained.norm.bias": (384,),
    "model.head.norm.weight": (768,),
    "model.head.projects.0.weight": (48, 768, 1, 1),
    "model.head.projects.3.bias": (384,),
    "model.head.resize_layers.0.weight": (48, 48, 4, 4),
    "model.head.resize_layers.1.weight": (96, 96, 2, 2),
    "model.head.resize_layers.3.weight": (384, 384, 3, 3),
    "model.head.scratch.layer1_rn.weight": (64, 48, 3, 3),
    "model.head.scratch.layer4_rn.weight": (64, 384, 3, 3),
    "model.head.scratch.refinenet1.resConfUnit1.conv1.weight": (64, 64, 3, 3),
    "model.head.scratch.refinenet1.out_conv.bias": (64,),
    "model.head.scratch.refinenet4.resConfUnit2.conv1.weight": (64, 64, 3, 3),
    "model.head.scratch.output_conv1.weight": (32, 64, 3, 3),
    "model.head.scratch.output_conv2.0.weight": (32, 32, 3, 3),
    "model.head.scratch.output_conv2.2.bias": (2,),
    "model.head.scratch.refinenet1_aux.resConfUnit1.conv1.weight": (64, 64, 3, 3),
    "model.head.scratch.refinenet4_aux.out_conv.bias": (64,),
    "model.head.scratch.output_conv1_aux.0.0.weight": (32, 64, 3, 3),
    "model.head.scratch.output_conv1_aux.3.4.bias": (32,),
    "model.head.scratch.output_conv2_aux.0.0.weight": (32, 32, 3, 3),
    "model.head.scratch.output_conv2_aux.3.2.weight": (32,),
    "model.head.scratch.output_conv2_aux.3.5.bias": (7,),
    "model.cam_dec.backbone.0.weight": (768, 768),
    "model.cam_dec.backbone.2.bias": (768,),
    "model.cam_dec.fc_t.weight": (3, 768),
    "model.cam_dec.fc_qvec.weight": (4, 768),
    "model.cam_dec.fc_fov.0.bias": (2,),
    "model.cam_enc.trunk.0.norm1.weight": (384,),
    "model.cam_enc.trunk.3.ls2.gamma": (384,),
    "model.cam_enc.token_norm.weight": (384,),
    "model.cam_enc.trunk_norm.bias": (384,),
    "model.cam_enc.pose_branch.fc1.weight": (192, 9),
    "model.cam_enc.pose_branch.fc2.weight": (384, 192),
}
#: keys absent by design: no registers, no qk-norm before block 4, no residual unit in refinenet4, no mask token
SMALL_ABSENT = (
    "model.backbone.pretrained.register_tokens",
    "model.backbone.pretrained.mask_token",
    "model.backbone.pretrained.blocks.3.attn.q_norm.weight",
    "model.head.scratch.refinenet4.resConfUnit1.conv1.weight",
)
BASE_KEYS = {
    "model.backbone.pretrained.pos_embed": (1, 1370, 768),
    "model.backbone.pretrained.blocks.4.attn.q_norm.weight": (64,),
    "model.head.norm.weight": (1536,),
    "model.head.projects.3.weight": (768, 1536, 1, 1),
    "model.head.scratch.layer4_rn.weight": (128, 768, 3, 3),
    "model.head.scratch.output_conv1.weight": (64, 128, 3, 3),
    "model.cam_dec.backbone.0.weight": (1536, 1536),
    "model.cam_enc.pose_branch.fc1.weight": (384, 9),
}
#: the whole state dict of the real network: (number of keys, number of values)
TOTALS = {"da3-small": (443, 34_299_655), "da3-base": (443, 135_366_791)}


@pytest.mark.parametrize(("name", "expected"), [("da3-small", SMALL_KEYS), ("da3-base", BASE_KEYS)])
def test_state_dict_matches_the_published_layout(name, expected):
    state = DepthAnything3(DA3Config(name)).state_dict()
    assert {k: tuple(state[k].shape) for k in expected if k in state} == expected
    assert (len(state), sum(v.numel() for v in state.values())) == TOTALS[name]
    assert all(k.startswith("model.") for k in state)  # image mean/std are not checkpoint entries
    if name == "da3-small":
        assert not set(SMALL_ABSENT) & state.keys()


def test_save_and_load_round_trip_bit_identical(small, tmp_path):
    small.save_pretrained(tmp_path)
    assert json.loads((tmp_path / "config.json").read_text()) == {"model_name": "da3-small"}
    assert load_file(str(tmp_path / "model.safetensors")).keys() == small.state_dict().keys() - TIED.keys()
    loaded = DepthAnything3.from_pretrained(tmp_path)
    assert not loaded.training
    for key, value in small.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    images = torch.rand(1, 2, 3, 28, 28)
    with torch.no_grad():
        a, b = small(images), loaded(images)
    assert all(torch.equal(a[k], b[k]) for k in a)


def test_a_checkpoint_saved_as_the_hub_saves_it_loads(small, tmp_path):
    """The hub's files hold 437 tensors: ``save_model`` drops the three tied copies of the aux
    LayerNorm (weight and bias); the loader fills them from level 0, and refuses ties that differ."""
    save_model(small, str(tmp_path / "model.safetensors"))  # the hub's way: tied tensors once
    (tmp_path / "config.json").write_text(json.dumps({"model_name": "da3-small"}))
    saved = load_file(str(tmp_path / "model.safetensors"))
    assert len(saved) == len(small.state_dict()) - 6 and not TIED.keys() & saved.keys()
    loaded = DepthAnything3.from_pretrained(tmp_path)
    for key, value in small.state_dict().items():
        assert torch.equal(loaded.state_dict()[key], value), key
    state = {k: v.clone() for k, v in small.state_dict().items()}
    name = next(iter(TIED))
    state[name] += 1  # a file whose tied copies disagree
    save_file(state, str(tmp_path / "model.safetensors"))
    with pytest.raises(ValueError, match=rf"{re.escape(name)} differs from .*shares one LayerNorm"):
        DepthAnything3.from_pretrained(tmp_path)


@pytest.mark.parametrize("views", [1, 2, 3])
def test_forward_shapes_and_finite(small, views):
    with torch.no_grad():
        out = small(torch.rand(1, views, 3, 42, 56))
    shapes = {k: tuple(v.shape) for k, v in out.items()}
    assert shapes == {
        "depth": (1, views, 42, 56), "depth_conf": (1, views, 42, 56), "conf": (1, views, 42, 56),
        "camera_poses": (1, views, 4, 4), "intrinsics": (1, views, 3, 3), "local_points": (1, views, 42, 56, 3),
    }  # fmt: skip
    assert all(torch.isfinite(v).all() for v in out.values())
    assert (out["depth"] > 0).all() and (out["depth_conf"] >= 1).all()
    assert torch.allclose(out["local_points"][..., 2], out["depth"])
    R = out["camera_poses"][..., :3, :3]
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=1e-5)


def test_three_or_more_views_come_back_in_input_order(small):
    """From three views on, a reference view is chosen by content and moved first; the outputs
    return to input order, so permuting the views permutes the depth."""
    torch.manual_seed(1)
    images = torch.rand(1, 4, 3, 28, 42)
    perm = torch.tensor([2, 0, 3, 1])
    with torch.no_grad():
        a, b = small(images)["depth"], small(images[:, perm])["depth"]
    assert torch.allclose(a[:, perm], b, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_half_precision_gives_no_nan(small, dtype):
    images = torch.rand(1, 2, 3, 28, 28)
    with torch.no_grad():
        cast = small(images.to(dtype))
        with torch.autocast("cpu", dtype=dtype):
            auto = small(images)
    for out in (cast, auto):
        assert all(torch.isfinite(v).all() for v in out.values())
        assert out["depth"].dtype == torch.float32  # head and camera decoder run in float32


def test_pose_encoding_and_unprojection():
    enc = torch.tensor([[[1.0, 2.0, 3.0, 0.0, 0.0, 0.0, 2.0, math.pi / 2, math.pi / 2]]])  # unnormalised identity
    c2w, K = pose_encoding_to_cameras(enc, 28, 42)
    assert torch.allclose(c2w[0, 0, :3, :3], torch.eye(3)) and torch.equal(c2w[0, 0, :3, 3], enc[0, 0, :3])
    assert torch.allclose(K[0, 0], torch.tensor([[21.0, 0, 21], [0, 14, 14], [0, 0, 1]]))
    points = unproject(torch.full((1, 28, 42), 2.0), K[0])
    assert torch.allclose(points[0, 13, 20], torch.tensor([-0.5 / 21 * 2, -0.5 / 14 * 2, 2.0]))


def test_loading_errors_name_the_file_and_the_problem(small, tmp_path):
    with pytest.raises(FileNotFoundError, match="config.json: missing"):
        DepthAnything3.from_pretrained(tmp_path)
    small.save_pretrained(tmp_path)
    config, weights = tmp_path / "config.json", tmp_path / "model.safetensors"

    config.write_text("{not json")
    with pytest.raises(ValueError, match="config.json: not valid JSON"):
        DepthAnything3.from_pretrained(tmp_path)
    config.write_text(json.dumps({"model_name": "da3-large"}))
    with pytest.raises(ValueError, match="model_name 'da3-large' is not one of.*CC BY-NC"):
        DepthAnything3.from_pretrained(tmp_path)
    config.write_text(json.dumps({"model_name": "da3-small"}))

    state = load_file(str(weights))
    del state["model.cam_dec.fc_t.bias"]
    state["model.extra"] = torch.zeros(1)
    state["model.head.norm.weight"] = torch.zeros(5)
    save_file(state, str(weights))
    with pytest.raises(ValueError) as err:
        DepthAnything3.from_pretrained(tmp_path)
    for part in ("model.safetensors", "missing keys (1): model.cam_dec.fc_t.bias", "unexpected keys (1): model.extra",
                 "model.head.norm.weight: file (5,) vs model (768,)"):  # fmt: skip
        assert part in str(err.value)

    weights.write_bytes(b"\x00" * 7)
    with pytest.raises(ValueError, match="model.safetensors: not a readable safetensors file"):
        DepthAnything3.from_pretrained(tmp_path)
    weights.unlink()
    with pytest.raises(FileNotFoundError, match="model.safetensors: missing"):
        DepthAnything3.from_pretrained(tmp_path)


def test_config_names_only_the_apache_models():
    assert DA3Config("da3-base").to_dict()["licence"] == "Apache-2.0"
    with pytest.raises(ValueError, match="da3-giant"):
        DA3Config("da3-giant")


def test_geometry_reconstructor_takes_a_da3_checkpoint(small, tmp_path):
    """``gensplat cache --reconstructor geometry --model DIR`` builds this through make_reconstructor:
    the checkpoint kind comes from its config, the weights' licence goes into the identity."""
    from gensplat_transforms.data.scenes import TabletopScene, default_cameras
    from gensplat_transforms.geometry.base import Views
    from gensplat_transforms.geometry.registry import make_reconstructor

    small.save_pretrained(tmp_path)
    rec = make_reconstructor({"name": "geometry", "model": str(tmp_path)})
    assert isinstance(rec.model, DepthAnything3) and not rec.metric  # depth up to scale: "auto" fits it
    assert rec.config()["model"] == {"architecture": "depth-anything-3", "name": "da3-small", "licence": "Apache-2.0"}
    assert rec.max_pixels == 504 * 504

    cameras = default_cameras(28, 28)[:2]
    images, _ = TabletopScene(seed=0).render(cameras)
    calibrated = rec.predict_depth(Views(images, cameras))
    assert calibrated.depths.shape == (2, 1, 28, 28) and torch.isfinite(calibrated.depths).all()
    uncalibrated = rec.predict_depth(Views(images, None))
    with torch.no_grad():
        K = small(images[None])["intrinsics"][0]
    assert torch.allclose(uncalibrated.cameras.K[:, :2, :2], K[:, :2, :2])  # DA3's own focal lengths
    assert rec.reconstruct(Views(images, cameras)).gaussians.means.shape[1] == 3
