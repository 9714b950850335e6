"""Issue 41: every mistake in the transform's items, model checkpoints, PLY files and preview
options gives a clear ValueError (a ``gensplat: error:`` line on the command line)."""

import json
import shutil

import pytest
import torch
from gensplat_cli import main
from plyfile import PlyData
from safetensors.torch import load_file, save_file
from tiny_model import tiny_model

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.geometry.model import GenSplatModel
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform

LEFT = "observation.images.left"


@pytest.fixture(scope="module")
def item_and_transform(tmp_path_factory):
    source = SceneEpisodes(num_episodes=2, num_frames=2, size=32)
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(2), progress=False)
    return SceneDataset(source)[0], GenSplatTransform(GenSplatConfig(probability=1.0, level="small"), cache)


@pytest.mark.parametrize("value", [1.01, -0.01, None])
def test_float_images_beyond_zero_one_are_refused(item_and_transform, value):
    item, tf = item_and_transform
    image = item[LEFT] * 255  # None: a float image in [0, 255]
    if value is not None:
        image = item[LEFT].clone()
        image[0, 2, 5] = value
    with pytest.raises(ValueError, match=rf"{LEFT}: float images must be in \[0, 1\] \(or uint8"):
        tf({**item, LEFT: image})


def test_float_images_within_rounding_of_the_range_pass(item_and_transform):
    item, tf = item_and_transform
    assert tf({**item, LEFT: item[LEFT] * (1 + 1e-4)})[LEFT].shape == item[LEFT].shape


@pytest.mark.parametrize("value", [float("inf"), float("-inf"), float("nan")])
def test_non_finite_pixels_are_refused(item_and_transform, value):
    item, tf = item_and_transform
    image = item[LEFT].clone()
    image[1, 3, 4] = value
    with pytest.raises(ValueError, match=f"{LEFT}: images must be finite"):
        tf({**item, LEFT: image})
    with pytest.raises(ValueError, match=f"{LEFT}: images must be finite"):
        tf({**item, LEFT: image.half()})


@pytest.mark.parametrize("key", ["episode_index", "frame_index"])
def test_fractional_indices_are_refused(item_and_transform, key):
    item, tf = item_and_transform
    for value in (torch.tensor(1.9), torch.tensor(0.5, dtype=torch.float64), 0.25, torch.tensor(float("nan"))):
        with pytest.raises(ValueError, match=f"{key} must be an integer"):
            tf({**item, key: value})
    assert tf({**item, key: torch.tensor(0.0)})[LEFT].shape == item[LEFT].shape


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    return tiny_model().save_pretrained(tmp_path_factory.mktemp("model") / "ckpt")


def _edit_config(meta_fields=None, **fields):
    def edit(path):
        meta = json.loads((path / "config.json").read_text())
        meta["config"].update(fields)
        (path / "config.json").write_text(json.dumps({**meta, **(meta_fields or {})}))

    return edit


def _edit_weights(edit):
    def apply(path):
        state = load_file(str(path / "model.safetensors"))
        edit(state)
        save_file(state, str(path / "model.safetensors"))

    return apply


def _nan(state):
    next(v for v in state.values() if v.is_floating_point()).view(-1)[0] = float("nan")


def _grow(state):
    key = next(iter(state))
    state[key] = torch.zeros(*state[key].shape[:-1], state[key].shape[-1] + 1)


BROKEN_CHECKPOINTS = {
    "config.json: not JSON": (lambda p: (p / "config.json").write_text("{not json"), r"config.json: not JSON"),
    "config.json: not UTF-8": (lambda p: (p / "config.json").write_bytes(b"\xff\xfe{"), r"config.json: not JSON"),
    "config.json: a list": (lambda p: (p / "config.json").write_text("[1]"), r"config.json: expected a JSON object"),
    "config: not an object": (_edit_config({"config": [32]}), r"config.json: ModelConfig: expected an object of"),
    "dim a string": (_edit_config(dim="32"), r"config.json: ModelConfig: wrong field types: dim='32'"),
    "dim a float": (_edit_config(dim=32.5), r"config.json: ModelConfig: wrong field types: dim=32.5"),
    "gs_taps a string": (_edit_config(gs_taps="0123"), r"config.json: .*gs_taps='0123'"),
    "dim absurd": (_edit_config(dim=10**30), r"config.json: ModelConfig: sizes beyond any real model: \['dim=1"),
    "grid absurd": (_edit_config(enc_pos_grid=10**6), r"config.json: .*beyond any real model: \['enc_pos_grid=1000000'"),
    "another size": (_edit_config(dim=64, head_dim=64), r"model.safetensors: does not fit the model .*shape mismatches"),
    "missing keys": (_edit_weights(lambda s: s.pop(next(iter(s)))), r"model.safetensors: does not fit .*missing: "),
    "unexpected keys": (_edit_weights(lambda s: s.update(extra=torch.zeros(2))), r"model.safetensors: does not fit .*unexpected: extra"),
    "wrong shape": (_edit_weights(_grow), r"model.safetensors: does not fit the model .*shape mismatches: .*: file"),
    "not safetensors": (lambda p: (p / "model.safetensors").write_bytes(bytes(64)), r"model.safetensors: not a rea"),
    "truncated": (lambda p: (p / "model.safetensors").write_bytes((p / "model.safetensors").read_bytes()[:-100]),
                  r"model.safetensors: not a readable safetensors file"),
    "NaN weights": (_edit_weights(_nan), r"model.safetensors: NaN or Inf weights in "),
}  # fmt: skip


@pytest.mark.parametrize("case", BROKEN_CHECKPOINTS)
def test_malformed_checkpoints_raise_value_errors_naming_the_file(checkpoint, tmp_path, case):
    corrupt, message = BROKEN_CHECKPOINTS[case]
    path = shutil.copytree(checkpoint, tmp_path / "ckpt")
    corrupt(path)
    with pytest.raises(ValueError, match=f"{path}/{message}"):
        GenSplatModel.from_pretrained(path)


def test_an_intact_checkpoint_loads(checkpoint):
    model = GenSplatModel.from_pretrained(checkpoint)
    torch.testing.assert_close(model.state_dict(), tiny_model().state_dict())


def _ply_with_count(path, text, declared):
    """Write random Gaussians as a PLY (ASCII when ``text``), then set its header's vertex count."""
    gen = torch.Generator().manual_seed(0)
    g = Gaussians(means=torch.randn(5, 3, generator=gen), quats=torch.randn(5, 4, generator=gen),
                  scales=torch.rand(5, 3, generator=gen) + 0.1, opacities=torch.rand(5, generator=gen) * 0.8 + 0.1,
                  sh=torch.randn(5, 1, 3, generator=gen))  # fmt: skip
    g.to_ply(path)
    if text:
        PlyData(PlyData.read(str(path), mmap=False).elements, text=True).write(str(path))
    data = path.read_bytes()
    path.write_bytes(data.replace(b"element vertex 5\n", f"element vertex {declared}\n".encode(), 1))
    return g


@pytest.mark.parametrize("text", [False, True])
@pytest.mark.parametrize("declared", [10**11, 6, 4, 0])
def test_ply_vertex_counts_unlike_the_body_are_refused(tmp_path, text, declared):
    path = tmp_path / "g.ply"
    _ply_with_count(path, text, declared)
    with pytest.raises(ValueError, match=f"{path}: .*the header declares {declared} vertex .* but the body has"):
        Gaussians.from_ply(path)


@pytest.mark.parametrize("text", [False, True])
def test_ply_vertex_count_equal_to_the_body_loads(tmp_path, text):
    g = _ply_with_count(tmp_path / "g.ply", text, 5)
    torch.testing.assert_close(Gaussians.from_ply(tmp_path / "g.ply").means, g.means)


@pytest.mark.parametrize("seed", [2**70, 2**64, -1])
def test_preview_seeds_out_of_torch_range_are_gensplat_errors(tmp_path, capsys, seed):
    args = ["preview", "--root", str(tmp_path / "data"), "--repo-id", "local/x", "--out", str(tmp_path / "out")]
    assert main([*args, "--seed", str(seed)]) == 2
    assert capsys.readouterr().err == (
        f"gensplat: error: gensplat preview: seed must be in [0, 2**64) (a torch seed), got {seed}\n"
    )


def test_a_hub_id_that_cannot_be_fetched_is_a_clear_error(monkeypatch):
    """Offline (or no such repository): a ValueError naming the id and the fix, not the hub
    library's own exception."""
    pytest.importorskip("huggingface_hub")
    from gensplat_transforms.geometry.model.checkpoints import resolve

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(ValueError, match=r"'someone/no-such-model' is not a local directory and could not be fetched"):
        resolve("someone/no-such-model")
