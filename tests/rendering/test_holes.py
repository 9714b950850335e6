"""Hole filling: covered pixels unchanged, holes take the surrounding colour, hard inputs."""

import os
import subprocess
import sys
import textwrap

import pytest
import torch
import torch.nn.functional as F

from gensplat_transforms.rendering.holes import _halve, _pull_push, fill_holes


def constant(rgb, h=24, w=20, b=1):
    return torch.tensor(rgb, dtype=torch.float32).reshape(1, 3, 1, 1).expand(b, 3, h, w).clone()


def test_fully_covered_image_is_unchanged():
    color = torch.rand(2, 3, 17, 23)
    alpha = torch.ones(2, 1, 17, 23)
    assert torch.equal(fill_holes(color, alpha), color)


def test_hole_in_a_uniform_region_takes_its_colour():
    color, alpha = constant((0.2, 0.5, 0.9)), torch.ones(1, 1, 24, 20)
    color[..., 5:15, 3:12] = 0
    alpha[..., 5:15, 3:12] = 0
    out = fill_holes(color, alpha, empty=(1.0, 0.0, 0.0))
    torch.testing.assert_close(out, constant((0.2, 0.5, 0.9)), atol=1e-6, rtol=0)


def test_partly_covered_edge_blends_with_its_neighbours_not_with_black():
    color, alpha = constant((0.8, 0.8, 0.8)), torch.ones(1, 1, 24, 20)
    alpha[..., :, 10] = 0.5
    color[..., :, 10] *= 0.5  # premultiplied, as rendered over black
    out = fill_holes(color, alpha)
    torch.testing.assert_close(out[..., :, 10], torch.full((1, 3, 24), 0.8), atol=1e-6, rtol=0)


def test_hole_between_two_colours_is_a_blend_of_both():
    color, alpha = torch.zeros(1, 3, 16, 32), torch.ones(1, 1, 16, 32)
    color[:, 0, :, :12] = 1.0  # red left, blue right, a gap between
    color[:, 2, :, 20:] = 1.0
    color[..., 12:20] = 0
    alpha[..., 12:20] = 0
    out = fill_holes(color, alpha)
    gap = out[..., 12:20]
    assert (gap[:, 1] == 0).all() and (gap[:, 0] > 0.05).all() and (gap[:, 2] > 0.05).all()
    assert gap[:, 0, :, 0].mean() > gap[:, 0, :, -1].mean()  # redder near the red side


def test_empty_image_gets_the_empty_colour_and_images_are_independent():
    color = torch.stack([torch.zeros(3, 8, 8), constant((0.1, 0.2, 0.3), 8, 8)[0]])
    alpha = torch.stack([torch.zeros(1, 8, 8), torch.ones(1, 8, 8)])
    out = fill_holes(color, alpha, empty=(0.5, 0.25, 1.0))
    torch.testing.assert_close(out[0], constant((0.5, 0.25, 1.0), 8, 8)[0])
    torch.testing.assert_close(out[1], color[1])


@pytest.mark.parametrize("size", [(1, 2), (1, 9), (7, 5), (3, 64)])
def test_odd_and_tiny_sizes(size):
    color, alpha = constant((0.3, 0.3, 0.3), *size), torch.ones(1, 1, *size)
    alpha[..., 0, 0] = 0
    color[..., 0, 0] = 0
    out = fill_holes(color, alpha)
    assert out.shape == color.shape
    torch.testing.assert_close(out, constant((0.3, 0.3, 0.3), *size), atol=1e-6, rtol=0)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float64])
def test_low_and_high_precision_inputs(dtype):
    color, alpha = torch.rand(1, 3, 12, 12).to(dtype), (torch.rand(1, 1, 12, 12) > 0.5).to(dtype)
    out = fill_holes(color * alpha, alpha)
    assert out.dtype == (torch.float64 if dtype == torch.float64 else torch.float32)
    assert torch.isfinite(out).all() and out.min() >= 0 and out.max() <= 1


def test_nan_inf_and_out_of_range_alpha_give_finite_output():
    color, alpha = torch.rand(1, 3, 10, 10), torch.rand(1, 1, 10, 10)
    color[0, 0, 0, 0], color[0, 1, 2, 2], alpha[0, 0, 3, 3] = float("nan"), float("inf"), float("nan")
    alpha[0, 0, 4, 4], alpha[0, 0, 5, 5] = -1.0, 7.0
    assert torch.isfinite(fill_holes(color, alpha)).all()


def test_bad_inputs_raise_naming_the_problem():
    with pytest.raises(ValueError, match="color must be"):
        fill_holes(torch.zeros(3, 8, 8), torch.zeros(1, 8, 8))
    with pytest.raises(ValueError, match="alpha must be"):
        fill_holes(torch.zeros(1, 3, 8, 8), torch.zeros(1, 1, 8, 9))
    with pytest.raises(ValueError, match="empty must be"):
        fill_holes(torch.zeros(1, 3, 8, 8), torch.zeros(1, 1, 8, 8), empty=(float("nan"), 0, 0))


def plain_fill_holes(color, alpha, empty=(0.0, 0.0, 0.0)):
    """The pull-push written plainly: one pooling and one upsampling per tensor and level."""
    dtype = torch.float64 if color.dtype == torch.float64 else torch.float32
    c = torch.nan_to_num(color.to(dtype), nan=0.0, posinf=0.0, neginf=0.0)
    a = torch.nan_to_num(alpha.to(dtype), nan=0.0).clamp(0, 1)
    pyramid = [(c, a)]
    while max(c.shape[-2:]) > 1:
        c, a = F.avg_pool2d(c, 2, ceil_mode=True), F.avg_pool2d(a, 2, ceil_mode=True)
        pyramid.append((c, a))
    fill = torch.where(a > 1e-6, c / a.clamp_min(1e-6), torch.tensor(empty, dtype=dtype).reshape(1, 3, 1, 1))
    for c, a in reversed(pyramid[:-1]):
        fill = c + (1 - a) * F.interpolate(fill, size=c.shape[-2:], mode="bilinear", align_corners=False)
    return fill


def tensor_fill_holes(color, alpha, empty):
    """``fill_holes`` in tensor operations (what float64, CUDA and autograd inputs take)."""
    return _pull_push(color, alpha, torch.tensor(empty, dtype=color.dtype).reshape(1, 3, 1, 1))


@pytest.mark.parametrize("shape", [(1, 224, 224), (3, 96, 130), (2, 45, 38), (1, 1, 300), (2, 257, 129), (1, 1, 1)])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("path", [fill_holes, tensor_fill_holes])
def test_equals_the_plain_pull_push(shape, dtype, path):
    """Pooling colour and alpha together, strided sums for large levels, the upsampling as
    one-channel images, and the compiled pass float32 CPU images take change nothing beyond
    float rounding (float32 results lie 5e-6 from float64's here, so 2e-6 between two float32
    orders of the same sums)."""
    gen = torch.Generator().manual_seed(shape[1])
    b, h, w = shape
    alpha = (torch.rand(b, 1, h, w, generator=gen) * 1.6 - 0.3).clamp(0, 1).to(dtype)
    color = torch.rand(b, 3, h, w, generator=gen).to(dtype) * alpha
    got, want = path(color, alpha, (0.5, 0.2, 0.1)), plain_fill_holes(color, alpha, (0.5, 0.2, 0.1))
    assert got.dtype == want.dtype
    torch.testing.assert_close(got, want, atol=2e-6 if dtype == torch.float32 else 1e-12, rtol=0)


def test_images_without_pixels_are_returned_empty():
    for shape in [(0, 3, 8, 8), (2, 3, 0, 8), (1, 3, 5, 0)]:
        color = torch.zeros(shape, dtype=torch.float16)
        out = fill_holes(color, torch.zeros(shape[0], 1, *shape[2:]))
        assert out.shape == shape and out.dtype == torch.float32


@pytest.mark.parametrize("size", [(224, 224), (64, 130), (2, 2), (7, 8), (45, 38)])
def test_halving_is_the_ceil_mode_average_pooling(size):
    x = torch.rand(2, 4, *size)
    assert torch.equal(_halve(x), F.avg_pool2d(x, 2, ceil_mode=True))


def test_compiled_pass_is_cached_for_new_processes():
    """A new dataloader worker loads the compiled hole filling from numba's disk cache (a
    cold compile takes seconds) instead of compiling it."""
    fill_holes(torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 8))  # make sure this process compiled
    script = textwrap.dedent("""
        import torch
        from gensplat_transforms.rendering import holes
        holes.fill_holes(torch.rand(1, 3, 8, 8), torch.rand(1, 1, 8, 8))
        print(len(holes._pull_push_cpu.stats.cache_misses), len(holes._pull_push_cpu.stats.cache_hits))
    """)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120,
                          check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert tuple(map(int, done.stdout.split())) == (0, 1)
