"""render_batch's compiled disc rule: the plain rule's images, and a warning and the plain
rule where torch.compile fails (on CUDA the compiled rule is the default)."""

import warnings

import pytest
import torch
from torch.utils.data import default_collate

from gensplat_transforms.cache.builder import SceneDataset, SceneEpisodes, build_cache
from gensplat_transforms.cache.depth_codec import depth_from_words
from gensplat_transforms.cache.store import SceneCache
from gensplat_transforms.core.rotations import covariance_3d
from gensplat_transforms.geometry import RGBDReconstructor
from gensplat_transforms.geometry import rgbd as rule
from gensplat_transforms.rendering.batched import render_batch
from gensplat_transforms.transform import GenSplatConfig, GenSplatTransform

LEFT = "observation.images.left"


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    source = SceneEpisodes(num_episodes=1, num_frames=3, size=24)
    cache = SceneCache(tmp_path_factory.mktemp("cache"), RGBDReconstructor(), source.fingerprint)
    build_cache(cache, source, range(1), progress=False)
    transform = GenSplatTransform(GenSplatConfig(probability=1.0, render_in="batch", level="large"), cache)
    ds = SceneDataset(source)
    torch.manual_seed(0)
    return default_collate([transform(ds[i]) for i in range(3)]), transform


def test_a_failing_compiler_warns_and_renders_with_the_plain_rule(prepared, monkeypatch):
    batch, transform = prepared
    calls = []

    def broken_compile(fn, **kwargs):
        def compiled(*args):
            calls.append(1)
            raise RuntimeError("no compiler here")
        return compiled

    monkeypatch.setattr(rule.torch, "compile", broken_compile)
    monkeypatch.setattr(rule, "_COMPILED", {})
    plain = render_batch(batch, transform, compiled=False)
    assert not calls
    with pytest.warns(RuntimeWarning, match="torch.compile of the disc rule failed.*no compiler here"):
        got = render_batch(batch, transform, compiled=True)
    assert torch.equal(got[LEFT], plain[LEFT])
    again = render_batch(batch, transform, compiled=True)  # no second try, no second warning
    assert len(calls) == 1 and torch.equal(again[LEFT], plain[LEFT])


def test_the_compiled_rule_is_called_when_asked_for(prepared, monkeypatch):
    batch, transform = prepared
    seen = []

    def tracing_compile(fn, **kwargs):
        assert kwargs == {"dynamic": True}

        def compiled(*args):
            seen.append(args[0].shape)
            return fn(*args)
        return compiled

    monkeypatch.setattr(rule.torch, "compile", tracing_compile)
    monkeypatch.setattr(rule, "_COMPILED", {})
    plain = render_batch(batch, transform)  # on the CPU: the plain rule by default
    assert not seen
    got = render_batch(batch, transform, compiled=True)
    assert seen == [torch.Size([3, 2, 24, 24])]  # (S * T, V, h, w) depth of the augmented samples
    assert torch.equal(got[LEFT], plain[LEFT])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="the compiled rule is the default on CUDA only")
def test_on_cuda_the_compiled_rule_builds_the_plain_rules_discs(prepared, monkeypatch):
    batch, transform = prepared
    rgbd = transform.cache.reconstructor
    depth = rgbd.disc_depth(depth_from_words(batch["gensplat.depth"], batch["gensplat.coded"].reshape(-1, 1, 1, 1, 1)))
    images = torch.rand(*depth.shape[:3], 3, *depth.shape[-2:])
    args = [t.cuda() for t in (depth, images, batch["gensplat.K"].float(), batch["gensplat.c2w"].float())]
    monkeypatch.setattr(rule, "_COMPILED", {})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        compiled = rule.compiled_discs(*args, rgbd.cfg)
    assert not [w for w in caught if "disc rule failed" in str(w.message)]  # a fallback would hide a failure
    assert rule._COMPILED["rule"] is not rule.dense_discs
    (means, quats, scales, dc, opacities, keep), plain = compiled, rule.dense_discs(*args, rgbd.cfg)
    assert torch.equal(keep, plain[5])
    torch.testing.assert_close(opacities, plain[4], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(means, plain[0], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(dc, plain[3], rtol=1e-5, atol=1e-6)
    # a round disc's in-plane angle is arbitrary (atan2 of round-off): compare the covariances
    cov, expected = (covariance_3d(q[keep], s[keep]) for q, s in ((quats, scales), (plain[1], plain[2])))
    torch.testing.assert_close(cov, expected, rtol=1e-4, atol=1e-5 * expected.abs().amax().item())
