"""MoGe-2 (microsoft/MoGe, MIT): config, checkpoint layouts, inference, and equivalence with the
official code.

No real weights are used: every checkpoint is written by the test, from random weights. The
official layout (``model.pt``: ``{"model_config": ..., "model": state dict}``) and the keys below
were read off ``moge/model/v2.py`` and its modules. The equivalence tests run only where
``MOGE_SOURCE`` names a folder holding the official ``moge`` package and its imports (utils3d,
scipy, cv2, huggingface_hub) are importable.
"""

from __future__ import annotations

import copy
import importlib
import json
import math
import os
import sys
import warnings

import pytest
import torch
from safetensors.torch import load_file, save_file
from tiny_moge import TINY, randomize

from gensplat_transforms.geometry.model.moge import (
    VITL_CONFIG,
    MoGe2,
    MoGe2Config,
    intrinsics_in_pixels,
    model_config,
    recover_focal_shift,
    token_grid,
)

#: the released MoGe-2 ViT-L (normal) architecture, configs/train/v2.json
VITL = VITL_CONFIG
#: a subset of the ViT-L state dict: (key, shape) as the official modules name and shape them
VITL_KEYS = {
    "encoder.image_mean": (1, 3, 1, 1),
    "encoder.backbone.cls_token": (1, 1, 1024),
    "encoder.backbone.pos_embed": (1, 1370, 1024),
    "encoder.backbone.mask_token": (1, 1024),
    "encoder.backbone.patch_embed.proj.weight": (1024, 3, 14, 14),
    "encoder.backbone.blocks.0.attn.qkv.weight": (3072, 1024),
    "encoder.backbone.blocks.0.attn.qkv.bias": (3072,),
    "encoder.backbone.blocks.23.ls2.gamma": (1024,),
    "encoder.backbone.blocks.23.mlp.fc1.weight": (4096, 1024),
    "encoder.backbone.norm.bias": (1024,),
    "encoder.output_projections.3.weight": (1024, 1024, 1, 1),
    "neck.input_blocks.0.weight": (1024, 1026, 1, 1),
    "neck.input_blocks.4.weight": (32, 2, 1, 1),
    "neck.resamplers.0.0.weight": (1024, 256, 2, 2),
    "neck.resamplers.0.1.weight": (256, 256, 3, 3),
    "neck.resamplers.3.1.weight": (32, 64, 3, 3),
    "neck.res_blocks.1.1.layers.2.weight": (256, 256, 3, 3),
    "neck.res_blocks.3.1.layers.5.bias": (64,),
    "points_head.output_blocks.4.weight": (3, 32, 1, 1),
    "mask_head.output_blocks.4.bias": (1,),
    "normal_head.input_blocks.0.weight": (1024, 1024, 1, 1),
    "normal_head.res_blocks.1.0.layers.5.weight": (256, 256, 3, 3),
    "scale_head.0.weight": (1024, 1024),
    "scale_head.4.weight": (1, 1024),
}
VITL_ABSENT = ("encoder.backbone.register_tokens", "neck.output_blocks.0.weight", "neck.res_blocks.0.0.layers.0.weight",
               "neck.res_blocks.1.2.layers.2.weight", "points_head.res_blocks.1.1.layers.2.weight")  # fmt: skip
#: keys and values of the official ViT-L state dict, counted on the official model
VITL_TOTALS = (521, 330_901_550)


@pytest.fixture(scope="module")
def tiny() -> MoGe2:
    return randomize(MoGe2(MoGe2Config.from_dict(TINY))).eval()


def tilted_plane(batch: int, H: int, W: int, fov_x: float, shift: float) -> tuple[torch.Tensor, torch.Tensor]:
    """An affine point map (B, H, W, 3) of a bumpy tilted plane seen with a horizontal FoV ``fov_x``
    (degrees), its z lowered by ``shift``; and its metric depth (B, H, W)."""
    f_px = W / 2 / math.tan(math.radians(fov_x) / 2)
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    depth = 3.0 + 1.5 * (v / H - 0.5) + 0.2 * torch.sin(u / W * 12) * torch.cos(v / H * 9)
    depth = depth.expand(batch, H, W) * torch.linspace(1, 2, batch)[:, None, None]
    x, y = (u - W / 2) / f_px * depth, (v - H / 2) / f_px * depth
    return torch.stack([x, y, depth - shift], dim=-1), depth


def images_of(kind: str, batch: int, H: int, W: int) -> torch.Tensor:
    gen = torch.Generator().manual_seed(1)
    if kind == "random":
        return torch.rand(batch, 3, H, W, generator=gen)
    if kind == "gradient":  # a rendered ramp: brightness falls with the rows, hue shifts with the columns
        v, u = torch.meshgrid(torch.linspace(0, 1, H), torch.linspace(0, 1, W), indexing="ij")
        return torch.stack([1 - v, u * (1 - v), 0.5 * (u + v)]).expand(batch, 3, H, W).contiguous()
    return torch.full((batch, 3, H, W), float(kind))  # a constant image


# ---------------------------------------------------------------- configuration and layout
def test_state_dict_matches_the_official_layout():
    with torch.device("meta"):
        state = MoGe2(MoGe2Config.from_dict(VITL)).state_dict()
    assert {k: tuple(state[k].shape) for k in VITL_KEYS if k in state} == VITL_KEYS
    assert not set(VITL_ABSENT) & state.keys()
    assert (len(state), sum(v.numel() for v in state.values())) == VITL_TOTALS
    reg = model_config("dinov2_vits14_reg", [384, 64, 32, 16, 8], [384, 1], 4, normal=False)
    with torch.device("meta"):
        state = MoGe2(MoGe2Config.from_dict(reg)).state_dict()
    assert state["encoder.backbone.register_tokens"].shape == (1, 4, 384)
    assert "encoder.output_projections.3.weight" in state and not any(k.startswith("normal_head") for k in state)


def test_config_round_trip_and_per_level_shorthands():
    cfg = MoGe2Config.from_dict(VITL)
    assert MoGe2Config.from_dict(cfg.to_dict()) == cfg
    official = cfg.to_dict()  # per-level lists, defaults written out: what MoGeModel(**config) takes
    assert official["neck"]["dim_out"] == [None] * 5 and official["neck"]["dim_times_res_block_hidden"] == 1
    assert {k: official["mask_head"][k] for k in VITL["mask_head"]} == VITL["mask_head"]
    assert cfg.taken_blocks == (5, 11, 17, 23) and cfg.width == 1024
    short = copy.deepcopy(TINY)
    short["neck"]["resamplers"] = "conv_transpose"  # the official stack also takes one value for all levels
    short["neck"]["num_res_blocks"] = 1
    short["encoder"]["intermediate_layers"] = 4
    cfg = MoGe2Config.from_dict(short)
    assert cfg.neck.resamplers == ("conv_transpose",) * 4 and cfg.neck.num_res_blocks == (1,) * 5
    assert cfg.taken_blocks == (8, 9, 10, 11)
    assert "normal_head" not in MoGe2Config.from_dict({**TINY, "normal_head": None}).to_dict()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (lambda c: c.pop("scale_head"), r"missing \['scale_head'\]"),
        (lambda c: c["encoder"].update(backbone="dinov2_vitg14"), "backbone 'dinov2_vitg14' is not one of"),
        (lambda c: c["encoder"].update(intermediate_layers=[2, 12]), "intermediate_layers .* outside the 12"),
        (lambda c: c["neck"].update(dim_in=[33, 2, 2, 2, 2]), r"neck: needs 5 levels with dim_in"),
        (lambda c: c["mask_head"].update(dim_out=[None] * 4 + [2]), "mask_head: the last level must give 1"),
        (lambda c: c["points_head"].update(dim_in=[32, 16, 16, 8, 9]), "points_head: its 5 input widths"),
        (lambda c: c["scale_head"].update(dims=[256, 1]), "scale_head: dims must run from 384 to 1"),
        (lambda c: c["neck"].update(resamplers=["conv_transpose"] * 2), r"neck.resamplers: expected 4 values"),
        (lambda c: c["neck"].update(resamplers=["avg_pool"] * 4), r"unsupported settings \['avg_pool'"),
        (lambda c: c["neck"].update(dim_res_blocks=[32, 16, "x", 8, 8]), "neck: widths must be positive integers"),
        (lambda c: c.update(remap_output="cube"), "remap_output 'cube'"),
        (lambda c: c["encoder"].pop("dim_out"), "malformed.*KeyError.*dim_out"),
    ],
)
def test_config_errors_say_what_is_wrong(change, message):
    cfg = copy.deepcopy(TINY)
    change(cfg)
    with pytest.raises(ValueError, match=message):
        MoGe2Config.from_dict(cfg)


def test_unknown_config_keys_are_ignored_with_a_warning():
    with pytest.warns(UserWarning, match=r"ignoring unknown keys \['trained_area_range'\]"):
        MoGe2Config.from_dict({**TINY, "trained_area_range": [1, 2]})


# ---------------------------------------------------------------- checkpoints
def _outputs_equal(a: MoGe2, b: MoGe2) -> None:
    images = images_of("random", 1, 28, 42)
    ra, rb = a.infer(images, num_tokens=6), b.infer(images, num_tokens=6)
    assert ra.keys() == rb.keys() and all(torch.equal(ra[k], rb[k]) for k in ra)


def test_official_and_safetensors_layouts_load_identically(tiny, tmp_path):
    official, converted = tmp_path / "official", tmp_path / "converted"
    official.mkdir()
    torch.save({"model_config": TINY, "model": tiny.state_dict()}, official / "model.pt")
    loaded = MoGe2.from_pretrained(official)
    assert not loaded.training and loaded.config == tiny.config
    _outputs_equal(tiny, loaded)

    loaded.save_pretrained(converted)
    meta = json.loads((converted / "config.json").read_text())
    assert meta == {"architecture": "moge-2", "licence": "MIT", "model_config": tiny.config.to_dict()}
    assert load_file(str(converted / "model.safetensors")).keys() == tiny.state_dict().keys()
    assert sorted(p.name for p in converted.iterdir()) == ["config.json", "model.safetensors"]  # no temporaries
    again = MoGe2.from_pretrained(converted)
    for key, value in tiny.state_dict().items():
        assert torch.equal(again.state_dict()[key], value), key
    _outputs_equal(tiny, again)


def test_the_image_statistics_buffers_may_be_absent(tiny, tmp_path):
    state = {k: v for k, v in tiny.state_dict().items() if not k.startswith("encoder.image_")}
    torch.save({"model_config": TINY, "model": state}, tmp_path / "model.pt")
    loaded = MoGe2.from_pretrained(tmp_path)
    assert torch.equal(loaded.encoder.image_std, tiny.encoder.image_std)


def test_loader_errors_name_the_file_and_the_keys(tiny, tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere: no such directory"):
        MoGe2.from_pretrained(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="holds neither model.pt nor config.json"):
        MoGe2.from_pretrained(tmp_path)

    pt = tmp_path / "model.pt"
    state = dict(tiny.state_dict())
    del state["scale_head.2.bias"]
    state["extra.weight"] = torch.zeros(1)
    state["neck.input_blocks.0.weight"] = torch.zeros(3, 3, 1, 1)
    torch.save({"model_config": TINY, "model": state}, pt)
    with pytest.raises(ValueError) as err:
        MoGe2.from_pretrained(tmp_path)
    for part in ("model.pt: does not fit", "missing keys (1): scale_head.2.bias", "unexpected keys (1): extra.weight",
                 "neck.input_blocks.0.weight: file (3, 3, 1, 1) vs model (32, 34, 1, 1)"):  # fmt: skip
        assert part in str(err.value)

    pt.write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="model.pt: not a readable torch checkpoint"):
        MoGe2.from_pretrained(tmp_path)
    torch.save({"model": tiny.state_dict()}, pt)
    with pytest.raises(ValueError, match="model.pt: not a MoGe checkpoint"):
        MoGe2.from_pretrained(tmp_path)
    torch.save({"model_config": {**TINY, "scale_head": None}, "model": {}}, pt)
    with pytest.raises(ValueError, match=r"model.pt: model_config: missing \['scale_head'\]"):
        MoGe2.from_pretrained(tmp_path)

    save_file({"x": torch.zeros(1)}, str(tmp_path / "model.safetensors"))  # the converted layout wins
    with pytest.raises(FileNotFoundError, match="config.json: missing"):
        MoGe2.from_pretrained(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"model_name": "da3-small"}))
    with pytest.raises(ValueError, match="config.json: not a MoGe-2 config"):
        MoGe2.from_pretrained(tmp_path)
    (tmp_path / "config.json").write_text(json.dumps({"architecture": "moge-2", "model_config": TINY}))
    with pytest.raises(ValueError, match=r"model.safetensors: does not fit.*unexpected keys \(1\): x"):
        MoGe2.from_pretrained(tmp_path)
    (tmp_path / "model.safetensors").write_bytes(b"\x00" * 9)
    with pytest.raises(ValueError, match="model.safetensors: not a readable safetensors file"):
        MoGe2.from_pretrained(tmp_path)


# ---------------------------------------------------------------- inference
def test_infer_outputs_shapes_dtypes_and_consistency(tiny):
    out = tiny.infer(images_of("random", 2, 42, 56), num_tokens=12)
    shapes = {k: (tuple(v.shape), v.dtype) for k, v in out.items()}
    f32 = torch.float32
    assert shapes == {
        "points": ((2, 42, 56, 3), f32), "depth": ((2, 42, 56), f32), "mask": ((2, 42, 56), torch.bool),
        "intrinsics": ((2, 3, 3), f32), "fov_x": ((2,), f32), "fov_y": ((2,), f32), "metric_scale": ((2,), f32),
        "normal": ((2, 42, 56, 3), f32),
    }  # fmt: skip
    assert all(v.isfinite().all() for v in out.values())
    mask, K = out["mask"], out["intrinsics"]
    assert mask.any() and (out["depth"][mask] > 0).all() and (out["depth"][~mask] == 0).all()
    assert torch.equal(out["points"][..., 2], out["depth"])
    assert torch.equal(K[:, :, 2], torch.tensor([0.5, 0.5, 1.0]).expand(2, 3)) and (K[:, 0, 1] == 0).all()
    v, u = 10, 33  # a pixel centre projects back onto itself
    x, y, z = out["points"][0, v, u]
    if mask[0, v, u]:
        assert torch.allclose(torch.stack([K[0, 0, 0] * x / z + 0.5, K[0, 1, 1] * y / z + 0.5]),
                              torch.tensor([(u + 0.5) / 56, (v + 0.5) / 42]), atol=1e-6)  # fmt: skip
    unit = out["normal"][mask].norm(dim=-1)
    assert torch.allclose(unit, torch.ones_like(unit), atol=1e-5)
    assert torch.allclose(out["fov_x"], torch.rad2deg(2 * torch.atan(0.5 / K[:, 0, 0])))


@pytest.mark.parametrize("kind", ["random", "gradient", "0", "1", "0.5"])
def test_no_nan_or_inf_leaves_infer(tiny, kind):
    for H, W in [(28, 42), (14, 200)]:
        out = tiny.infer(images_of(kind, 1, H, W), num_tokens=8)
        assert all(v.isfinite().all() for k, v in out.items() if k != "mask"), (kind, H, W)


def test_an_all_invalid_mask_gives_zeros_and_the_default_focal(tiny):
    model = copy.deepcopy(tiny)
    with torch.no_grad():
        model.mask_head.output_blocks[-1].bias.fill_(-30.0)
    out = model.infer(images_of("random", 1, 28, 28), num_tokens=4)
    assert not out["mask"].any() and not out["depth"].any() and not out["points"].any() and not out["normal"].any()
    assert torch.allclose(out["intrinsics"][0, 0, 0], torch.tensor(2**0.5 / 2))  # focal 1 of half the diagonal


def test_a_model_without_normal_head(tiny):
    model = randomize(MoGe2(MoGe2Config.from_dict({**TINY, "normal_head": None})))
    assert "normal" not in model.infer(images_of("random", 1, 28, 28), num_tokens=4)


def test_fp16_autocast_stays_finite(tiny):
    out = tiny.infer(images_of("random", 1, 28, 42), num_tokens=6, fp16=True)
    assert out["depth"].dtype == torch.float32 and all(v.isfinite().all() for v in out.values())


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"images": torch.rand(3, 28, 28)}, r"\(B, 3, H, W\) tensor, got \(3, 28, 28\)"),
        ({"images": torch.rand(1, 4, 28, 28)}, r"got \(1, 4, 28, 28\)"),
        ({"images": torch.rand(1, 3, 0, 28)}, "non-empty"),
        ({"images": torch.zeros(1, 3, 28, 28, dtype=torch.uint8)}, "floating point"),
        ({"images": torch.full((1, 3, 28, 28), math.nan)}, "NaN or Inf"),
        ({"images": torch.full((1, 3, 28, 28), 255.0)}, r"must lie in \[0, 1\]"),
        ({"images": [[0.5]]}, "got list"),
        ({"num_tokens": 0}, "num_tokens must be a positive integer"),
        ({"resolution_level": 10}, "resolution_level must be an integer 0..9"),
        ({"fov_x": 180.0}, r"fov_x must be one or 1 angles in \(0, 180\)"),
        ({"fov_x": [60.0, 70.0]}, "fov_x must be one or 1 angles"),
    ],
)
def test_infer_validates_its_inputs(tiny, kwargs, message):
    kwargs = {"images": torch.rand(1, 3, 28, 28), **kwargs}
    with pytest.raises(ValueError, match=message):
        tiny.infer(**kwargs)


def test_token_grid_and_resolution_levels(tiny):
    assert token_grid(480, 640, 3600) == (52, 69) and token_grid(224, 224, 3600) == (60, 60)
    assert token_grid(10, 10_000, 4) == (1, 63)
    assert [tiny.num_tokens(level) for level in (0, 9)] == [1200, 3600] and tiny.num_tokens(5) == 2533


def test_intrinsics_in_pixels():
    K = torch.tensor([[0.8, 0.0, 0.5], [0.0, 1.1, 0.5], [0.0, 0.0, 1.0]])
    expected = torch.tensor([[512.0, 0.0, 320.0], [0.0, 528.0, 240.0], [0.0, 0.0, 1.0]])
    assert torch.allclose(intrinsics_in_pixels(K, 640, 480), expected)


@pytest.mark.parametrize("known_focal", [False, True])
def test_focal_and_shift_recovery_on_a_rendered_plane(known_focal):
    H, W, fov_x, shift = 48, 64, 60.0, 0.7
    points, _ = tilted_plane(2, H, W, fov_x, shift)
    aspect = W / H
    focal = aspect / math.hypot(1, aspect) / math.tan(math.radians(fov_x) / 2)  # of half the diagonal
    given = torch.full((2,), focal) if known_focal else None
    f, s = recover_focal_shift(points, torch.ones(2, H, W, dtype=torch.bool), given)
    assert torch.allclose(f, torch.full((2,), focal), rtol=1e-5) and torch.allclose(s, torch.full((2,), shift))


def test_infer_post_processing_recovers_a_rendered_plane(tiny, monkeypatch):
    """With the network replaced by a known affine point map, infer returns the metric scene."""
    H, W, fov_x, scale = 48, 64, 70.0, 2.5
    points, depth = tilted_plane(2, H, W, fov_x, shift=0.4)
    raw = {"points": points, "mask": torch.ones(2, H, W), "metric_scale": torch.full((2,), scale),
           "normal": torch.nn.functional.normalize(torch.ones(2, H, W, 3), dim=-1)}  # fmt: skip
    monkeypatch.setattr(tiny, "forward", lambda images, num_tokens: raw)
    for known in (None, fov_x):
        out = tiny.infer(torch.rand(2, 3, H, W), fov_x=known)
        assert out["mask"].all()
        assert torch.allclose(out["depth"], depth * scale, rtol=1e-5)
        assert torch.allclose(out["fov_x"], torch.full((2,), fov_x), rtol=1e-5)
        K = intrinsics_in_pixels(out["intrinsics"], W, H)
        assert torch.allclose(K[:, 0, 0], K[:, 1, 1]) and torch.allclose(K[0, :2, 2], torch.tensor([W / 2, H / 2]))
        assert torch.allclose(out["points"], torch.cat([points[..., :2], depth[..., None]], -1) * scale, rtol=1e-4,
                              atol=1e-5)  # fmt: skip


# ---------------------------------------------------------------- equivalence with the official code
@pytest.fixture(scope="module")
def official_v2():
    """The official ``moge.model.v2`` from ``MOGE_SOURCE`` (xFormers disabled: the plain attention)."""
    source = os.environ.get("MOGE_SOURCE")
    if not source:
        pytest.skip("MOGE_SOURCE is not set (a folder holding the official microsoft/MoGe 'moge' package)")
    if not os.path.isdir(os.path.join(source, "moge")):
        pytest.skip(f"MOGE_SOURCE={source} holds no 'moge' package")
    os.environ["XFORMERS_DISABLED"] = "1"  # DINOv2's layers read it at import; the CPU has no xFormers anyway
    sys.path.insert(0, source)
    try:
        v2 = importlib.import_module("moge.model.v2")
        geometry = importlib.import_module("moge.utils.geometry_torch")
    except ImportError as e:
        pytest.skip(f"the official MoGe code does not import here: {e} (it needs utils3d, scipy, cv2, "
                    "huggingface_hub)")  # fmt: skip
    finally:
        sys.path.remove(source)
    return v2, geometry


def _official_pair(v2, cfg: dict, seed: int):
    ours = randomize(MoGe2(MoGe2Config.from_dict(cfg)), seed).eval()
    official = v2.MoGeModel(**ours.config.to_dict()).eval()  # the config as save_pretrained writes it
    official.load_state_dict(ours.state_dict(), strict=True)  # the same keys and shapes, both ways
    return ours, official


def _max_diff(a: torch.Tensor, b: torch.Tensor) -> tuple[float, float]:
    err = (a.double() - b.double()).abs()
    return float(err.max()), float((err / b.double().abs().clamp_min(1e-6)).max())


EQUIVALENCE_CASES = [  # (backbone, intermediate layers, H, W, num_tokens)
    ("dinov2_vits14", [2, 5, 8, 11], 60, 80, 100),
    ("dinov2_vits14_reg", 4, 90, 50, 60),
]


def _equivalent_pair(v2, backbone: str, layers) -> tuple[MoGe2, torch.nn.Module]:
    cfg = {**TINY, "encoder": {**TINY["encoder"], "backbone": backbone, "intermediate_layers": layers}}
    return _official_pair(v2, cfg, seed=3)


def _official_infer(model, images, **kwargs) -> dict:
    with warnings.catch_warnings():  # its float32 post-processing opens a CPU autocast, which warns
        warnings.simplefilter("ignore", UserWarning)
        return model.infer(images, use_fp16=False, **kwargs)


@pytest.mark.parametrize(("backbone", "layers", "H", "W", "num_tokens"), EQUIVALENCE_CASES)
@pytest.mark.parametrize("kind", ["random", "gradient"])
def test_network_matches_the_official_code(official_v2, backbone, layers, H, W, num_tokens, kind):
    """The network's outputs (affine points, mask, normals, metric scale) to float32 noise, and the
    metric outputs of ``infer`` at a known field of view (the fit of the shift alone)."""
    ours, official = _equivalent_pair(official_v2[0], backbone, layers)
    images = images_of(kind, 2, H, W)
    with torch.no_grad():
        a, b = ours(images, num_tokens), official(images, num_tokens)
    assert a.keys() == b.keys() == {"points", "mask", "normal", "metric_scale"}
    for key in a:
        abs_err, _ = _max_diff(a[key], b[key])
        assert abs_err <= 1e-5 * float(b[key].abs().max()), (key, abs_err)
    _compare_infer(ours.infer(images, num_tokens=num_tokens, fov_x=60.0),
                   _official_infer(official, images, num_tokens=num_tokens, fov_x=60.0))  # fmt: skip


@pytest.mark.parametrize(("backbone", "layers", "H", "W", "num_tokens"), EQUIVALENCE_CASES)
def test_free_focal_fit_on_a_random_network_stays_close(official_v2, backbone, layers, H, W, num_tokens):
    """Random weights give a nearly constant z, whose focal-shift fit is ill-posed (a valley): both
    stop on the relative-reduction test, where the official finite-difference Jacobian and ours (exact)
    may part by ~1e-3. Well-posed maps agree to float32 noise (the post-processing test below)."""
    ours, official = _equivalent_pair(official_v2[0], backbone, layers)
    images = images_of("random", 2, H, W)
    _compare_infer(ours.infer(images, num_tokens=num_tokens), _official_infer(official, images,
                   num_tokens=num_tokens), rtol=1e-2)  # fmt: skip


@pytest.mark.parametrize("backbone", ["dinov2_vits14", "dinov2_vits14_reg"])
def test_position_embeddings_match_the_official_code(official_v2, backbone):
    ours, official = _equivalent_pair(official_v2[0], backbone, 4)
    for h, w in [(37, 37), (5, 7), (52, 69), (1, 11)]:  # 37 x 37: the learned grid as it is
        x = torch.zeros(1, 1 + h * w, 384)
        expected = official.encoder.backbone.interpolate_pos_encoding(x, h * 14, w * 14)
        assert torch.equal(ours.encoder.backbone.position_embedding(h, w), expected), (h, w)


def _compare_infer(ra: dict, rb: dict, rtol: float = 1e-5) -> dict[str, float]:
    """Ours vs official ``infer``: the same mask; on it the same points, depth and normals (the official
    code writes inf / 0 off the mask, ours 0); the same intrinsics: each within ``rtol`` of the largest
    value. Returns the max abs difference relative to the largest value, per key."""
    mask = rb["mask"]
    assert torch.equal(ra["mask"], mask) and mask.any()
    assert not ra["depth"][~mask].any() and torch.isinf(rb["depth"][~mask]).all()
    pairs = {"points": (ra["points"][mask], rb["points"][mask]), "depth": (ra["depth"][mask], rb["depth"][mask]),
             "intrinsics": (ra["intrinsics"], rb["intrinsics"])}  # fmt: skip
    if "normal" in rb:
        pairs["normal"] = (ra["normal"], rb["normal"])
    errors = {key: _max_diff(a, b)[0] / float(b.abs().max()) for key, (a, b) in pairs.items()}
    assert all(err <= rtol for err in errors.values()), errors
    return errors


@pytest.mark.parametrize("noise", [0.0, 0.01])
def test_post_processing_matches_the_official_code(official_v2, monkeypatch, noise):
    """Both ``infer`` on the same well-posed affine point map (a rendered plane, with noise), mask and
    metric scale: focal, shift, depth, points and mask agree to float32 noise."""
    v2, geometry = official_v2
    ours, official = _official_pair(v2, TINY, seed=0)
    H, W = 48, 64
    points, _ = tilted_plane(2, H, W, 55.0, shift=0.5)
    points = points * (1 + noise * torch.randn(points.shape, generator=torch.Generator().manual_seed(0)))
    mask = torch.ones(2, H, W)
    mask[:, :6] = 0.2  # an invalid band on top
    raw = {"points": points, "mask": mask, "metric_scale": torch.tensor([1.5, 0.8])}
    for model in (ours, official):  # each infer edits its points in place: give each a copy
        monkeypatch.setattr(model, "forward", lambda images, num_tokens: {k: v.clone() for k, v in raw.items()})
    images = torch.rand(2, 3, H, W)
    for fov_x in (None, 62.0):
        _compare_infer(ours.infer(images, fov_x=fov_x), _official_infer(official, images, fov_x=fov_x))
    f_ours, s_ours = recover_focal_shift(points, mask > 0.5)
    f_off, s_off = geometry.recover_focal_shift(points, mask > 0.5)
    assert torch.allclose(f_ours, f_off, rtol=1e-5) and torch.allclose(s_ours, s_off, rtol=1e-5, atol=1e-6)
