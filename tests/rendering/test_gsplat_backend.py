"""The optional "gsplat" backend: a clear error without CUDA or gsplat, agreement with the
fast backend where both are present."""

import builtins
import math

import pytest
import torch
from hard_cases import HARD_CASES

from gensplat_transforms import render
from gensplat_transforms.core.cameras import Cameras, look_at
from gensplat_transforms.core.gaussians import Gaussians
from gensplat_transforms.rendering import BACKENDS

needs_gsplat = pytest.mark.skipif(
    not torch.cuda.is_available(), reason="the gsplat backend needs a CUDA device"
)


def _import_gsplat():
    pytest.importorskip("gsplat", reason="the gsplat package is not installed (optional extra)")


def _scene(n: int = 400, seed: int = 0) -> tuple[Gaussians, Cameras]:
    gen = torch.Generator().manual_seed(seed)
    g = Gaussians(
        means=torch.rand(n, 3, generator=gen) - 0.5,
        quats=torch.randn(n, 4, generator=gen),
        scales=0.01 + 0.03 * torch.rand(n, 3, generator=gen),
        opacities=0.2 + 0.75 * torch.rand(n, generator=gen),
        sh=0.3 * torch.randn(n, 16, 3, generator=gen),
    )
    K = torch.tensor([[80.0, 0, 48], [0, 80.0, 40], [0, 0, 1]])
    c2w = look_at((1.2, -1.5, 1.0), (0.0, 0.0, 0.0)).float()
    return g, Cameras(K, c2w[None], 96, 80)


def test_registered():
    assert "gsplat" in BACKENDS


@pytest.mark.parametrize("missing", ["cuda", "gsplat"])
def test_clear_error_when_unavailable(monkeypatch, missing):
    """Runs everywhere: CUDA or gsplat is made unavailable, whatever the machine has."""
    if missing == "cuda":
        monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
        expected = "no CUDA device"
    else:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
        real_import = builtins.__import__

        def no_gsplat(name, *args, **kwargs):
            if name == "gsplat" or name.startswith("gsplat."):
                raise ImportError("No module named 'gsplat'")
            return real_import(name, *args, **kwargs)

        monkeypatch.setattr(builtins, "__import__", no_gsplat)
        expected = "gsplat is not importable"
    g, cam = _scene(10)
    with pytest.raises(RuntimeError, match=rf"gsplat backend needs CUDA and the gsplat package: {expected}"):
        render(g, cam, backend="gsplat")


@needs_gsplat
def test_agrees_with_fast_backend():
    _import_gsplat()
    g, cam = _scene()
    bg = (0.1, 0.2, 0.3)
    for degree in (0, 3):
        ours = render(g, cam, backend="fast", sh_degree=degree, background=bg)
        theirs = render(g, cam, backend="gsplat", sh_degree=degree, background=bg)
        mse = (ours.rgb - theirs.rgb).square().mean().item()
        assert 10 * math.log10(1 / max(mse, 1e-20)) > 35
        assert (ours.alpha - theirs.alpha).abs().mean() < 5e-3
        solid = (ours.alpha > 0.5) & (theirs.alpha > 0.5)
        rel = ((ours.depth - theirs.depth).abs() / ours.depth)[solid]
        assert rel.median() < 1e-3


@needs_gsplat
@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_finite_and_close_to_fast(name):
    """Every hard case of the core renderer: finite outputs, and the same picture as the
    fast backend up to the documented differences (alpha clamp 0.999, no 3-sigma cut)."""
    _import_gsplat()
    cam = Cameras.from_intrinsics(40.0, 44.0, 22.8, 18.8, torch.eye(4), 45, 38)
    bg = (0.5, 0.25, 1.0)
    ours = render(HARD_CASES[name], cam, backend="fast", background=bg)
    theirs = render(HARD_CASES[name], cam, backend="gsplat", background=bg)
    for t in (theirs.rgb, theirs.depth, theirs.alpha):
        assert torch.isfinite(t).all()
    if name == "needle":  # documented: gsplat's float32 projection drops it, ours draws it
        return
    assert (ours.alpha - theirs.alpha).abs().max() < 0.05
    assert (ours.rgb - theirs.rgb).abs().max() < 0.05
