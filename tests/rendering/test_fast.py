"""The compiled "fast" CPU backend agrees with the reference renderer, on random scenes and on
every hard case, for every thread count.

Tolerances: per pair the fast backend repeats the reference's float32 arithmetic except its
polynomial exponential (relative error < 2e-6) and a running transmittance product (the
reference sums float64 logarithms), so images agree to ~1e-6; 2e-5 leaves room for the
accumulation of many splats. A pair exactly on a threshold (alpha = 1/255, T = 1e-4) could in
principle flip; the seeded scenes here contain none.
"""

import math
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numba
import numpy as np
import pytest
import torch
from hard_cases import HARD_CASES, MAGNITUDES, SCALABLE_FIELDS, scaled

from gensplat_transforms import Cameras, Gaussians, render
from gensplat_transforms.core.cameras import look_at
from gensplat_transforms.rendering import BACKENDS, fast
from gensplat_transforms.rendering.projection import MAX_COLOR

W, H = 45, 38  # not multiples of the 16-pixel tile: edge tiles are partial
ATOL = 2e-5
# float64 scenes: the reference composites in float64, the fast backend in float32; for the
# needle (scales 1e3 and 1e-12 after the clamp) q = A dx^2 + 2B dx dy + C dy^2 cancels about
# 100x in float32, so alpha differs by up to 3e-5 there
ATOL_F64 = 1e-4


def camera(dtype=torch.float64, c2w=None, f=40.0) -> Cameras:
    c2w = torch.eye(4, dtype=dtype) if c2w is None else c2w.to(dtype)
    return Cameras.from_intrinsics(f, f * 1.1, W / 2 + 0.3, H / 2 - 0.2, c2w, W, H)


def random_scene(n=300, seed=0, dtype=torch.float32, sh_degree=3, scale=0.08) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.6, 0.5, 0.4]) + torch.tensor([0, 0, 2.0])
    return Gaussians(
        means=means.to(dtype),
        quats=torch.randn(n, 4, generator=g).to(dtype),
        scales=(torch.rand(n, 3, generator=g) * scale + 0.002).to(dtype),
        opacities=(torch.rand(n, generator=g) * 0.99).to(dtype),
        sh=(torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.4).to(dtype),
    )


def both(g: Gaussians, cam: Cameras, atol=ATOL, rtol=0.0, **kwargs):
    """Render with both backends, check agreement and finiteness; return the fast output.
    ``rtol`` adds a tolerance relative to each value (for huge colours and depths)."""
    ref = render(g, cam, backend="reference", **kwargs)
    out = render(g, cam, backend="fast", **kwargs)
    for name in ("rgb", "depth", "alpha"):
        r, f = getattr(ref, name), getattr(out, name)
        if r is None:
            assert f is None, name
            continue
        assert f.dtype == r.dtype and f.shape == r.shape, name
        assert torch.isfinite(r).all(), f"reference {name} has non-finite values"
        assert torch.isfinite(f).all(), f"fast {name} has non-finite values"
        # depth is a ratio sum(w z) / alpha: compare each pixel relative to its own depth
        rel = max(rtol, atol) if name == "depth" else rtol
        torch.testing.assert_close(f, r, atol=atol, rtol=rel, msg=lambda m, n=name: f"{n}: {m}")
    return out


def test_polynomial_exponential_is_accurate():
    coefficients = tuple(np.float32(v) for v in fast._CONSTANTS[9:])
    ys = np.linspace(-0.625, 0.0, 2001, dtype=np.float32)
    got = np.array([fast._exp8(y, coefficients) for y in ys])
    assert np.abs(got / np.exp(8 * ys.astype(np.float64)) - 1).max() < 2e-6


@pytest.mark.parametrize("n", [0, 1, 5000])
def test_depth_sort_is_stable(n):
    rng = np.random.default_rng(n)
    keys = rng.choice(rng.uniform(0.01, 50.0, max(1, n // 3)), n)  # many ties
    keys[: n // 10] = 1.0  # a run of equal keys
    want = np.argsort(keys, kind="stable")
    np.testing.assert_array_equal(fast._argsort_depth(keys), want)


def test_depth_sort_orders_keys_equal_in_float32():
    """The radix passes see float32 roundings; keys that differ only in float64 (and exact
    ties among them) must still come out in float64 order, ties by index."""
    rng = np.random.default_rng(0)
    base = rng.uniform(0.4, 2.5, 500).astype(np.float32).astype(np.float64)
    keys = np.concatenate([base + 1e-12, base, base, np.nextafter(base, 3.0), [1e300, 5e299, 1e300, 1e-300]])
    keys = keys[rng.permutation(keys.size)]
    with np.errstate(over="ignore"):  # 1e300 rounds to inf in float32, as in the sort
        assert np.unique(keys.astype(np.float32)).size < np.unique(keys).size
    np.testing.assert_array_equal(fast._argsort_depth(keys), np.argsort(keys, kind="stable"))


def test_registered_backend():
    assert BACKENDS["fast"] is fast.render_fast


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_scenes_agree_with_reference(seed):
    c2w = look_at((0.4, -0.3, -0.2), (0.0, 0.1, 2.0), up=(0.0, -1.0, 0.0))
    both(random_scene(seed=seed), camera(c2w=c2w), background=(0.2, 0.5, 0.9))


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 4])
def test_every_sh_degree_and_truncation(sh_degree):
    g = random_scene(n=150, seed=3, sh_degree=sh_degree)
    both(g, camera())
    both(g, camera(), sh_degree=max(sh_degree - 1, 0))


def test_dense_opaque_scene_stops_pixels_and_tiles():
    """Many large opaque splats: pixels reach the transmittance floor, whole tiles finish
    early; also with the reference split in chunks, which must carry the stop rule."""
    g = random_scene(n=1000, seed=4, scale=0.4)
    g = Gaussians(**{**g.tensors(), "opacities": torch.full((1000,), 0.99)})
    out = both(g, camera())
    assert (out.alpha > 0.999).float().mean() > 0.9
    chunked = render(g, camera(), backend="reference", max_pairs=512)
    torch.testing.assert_close(out.rgb, chunked.rgb, atol=ATOL, rtol=0)


def test_threads_give_identical_images():
    g = random_scene(n=2000, seed=5)
    one = render(g, camera(), backend="fast", threads=1)
    for threads in (2, numba.config.NUMBA_NUM_THREADS + 3):  # more than available is capped
        many = render(g, camera(), backend="fast", threads=threads)
        for name in ("rgb", "depth", "alpha"):
            assert torch.equal(getattr(one, name), getattr(many, name)), name


def test_threads_option_restores_numba_and_torch_settings():
    before, torch_before = numba.get_num_threads(), torch.get_num_threads()
    render(random_scene(n=50), camera(), backend="fast", threads=2)
    assert numba.get_num_threads() == before
    assert torch.get_num_threads() == torch_before
    with pytest.raises(ValueError, match="threads"):
        render(random_scene(n=5), camera(), backend="fast", threads=0)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork()")
@pytest.mark.filterwarnings("ignore:This process .* is multi-threaded:DeprecationWarning")
def test_single_thread_rendering_works_in_a_forked_child():
    """Dataloader workers are often forked from a process that rendered with threads > 1;
    threads=1 runs serial code, untouched by the parent's thread pool."""
    g = random_scene(n=200, seed=10)
    expected = render(g, camera(), backend="fast", threads=2).rgb
    pid = os.fork()
    if pid == 0:  # child: report through the exit status only
        ok = False
        try:
            ok = torch.equal(render(g, camera(), backend="fast", threads=1).rgb, expected)
        finally:
            os._exit(0 if ok else 1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


def test_background_and_return_flags():
    g = random_scene(n=100, seed=6)
    full = both(g, camera(), background=(1.0, 0.25, 0.0))
    lean = render(g, camera(), backend="fast", background=(1.0, 0.25, 0.0), return_depth=False,
                  return_alpha=False)  # fmt: skip
    assert lean.depth is None and lean.alpha is None
    assert torch.equal(lean.rgb, full.rgb)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_inputs(dtype):
    out = both(random_scene(n=200, seed=7, dtype=dtype), camera())
    assert out.rgb.dtype == torch.float32


def test_float64_scene_renders_in_float32_and_returns_float64():
    out = both(random_scene(n=200, seed=8, dtype=torch.float64), camera())
    assert out.rgb.dtype == torch.float64


def test_float32_camera():
    both(random_scene(n=200, seed=8), camera(dtype=torch.float32))


@pytest.mark.parametrize("backend", ["reference", "fast"])
def test_gaussians_changed_in_place_after_a_render_are_checked_again(backend):
    g = random_scene(n=50, seed=10)
    render(g, camera(), backend=backend)
    g.sh[7, 2, 1] = float("inf")
    with pytest.raises(ValueError, match=r"Gaussians.sh: 1 Gaussian\(s\) have NaN or Inf"):
        render(g, camera(), backend=backend)


@pytest.mark.parametrize("backend", ["reference", "fast"])
def test_writes_that_bypass_torchs_version_counter_are_caught_by_the_next_render(backend):
    """``.data`` and NumPy views share the storage but not the version counter: render
    rescans in full every time, so it still names the field instead of returning NaN."""
    g = random_scene(n=50, seed=10)
    render(g, camera(), backend=backend)
    g.sh.data[7, 0, 1] = float("nan")
    with pytest.raises(ValueError, match=r"Gaussians.sh: 1 Gaussian\(s\) have NaN or Inf"):
        render(g, camera(), backend=backend)
    g = random_scene(n=50, seed=10)
    render(g, camera(), backend=backend)
    g.scales.numpy()[3, 2] = -1.0
    with pytest.raises(ValueError, match=r"Gaussians.scales: scales must be >= 0"):
        render(g, camera(), backend=backend)


def test_recheck_false_trusts_a_passed_check_but_not_a_missing_or_outdated_one():
    """``recheck=False`` (the dataset transform's own Gaussians) skips the scan of tensors a
    check passed while torch saw no write; unchecked or changed tensors are still scanned."""
    g = random_scene(n=50, seed=10)
    g.sh[7, 0, 1] = float("nan")  # never checked: scanned
    with pytest.raises(ValueError, match=r"Gaussians.sh: 1 Gaussian\(s\) have NaN or Inf"):
        render(g, camera(), backend="fast", recheck=False)
    g = random_scene(n=50, seed=10)
    render(g, camera(), backend="fast")
    g.opacities[0] = 2.0  # a write torch saw: scanned again
    with pytest.raises(ValueError, match="opacities must lie in"):
        render(g, camera(), backend="fast", recheck=False)
    g = random_scene(n=50, seed=10)
    before = render(g, camera(), backend="fast")
    g.sh.data[7, 0, 1] = 0.5  # unseen by torch: trusted as documented, and drawn
    after = render(g, camera(), backend="fast", recheck=False)
    assert not torch.equal(before.rgb, after.rgb)
    torch.testing.assert_close(after.rgb, render(g, camera(), backend="fast").rgb, rtol=0, atol=0)


@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_agree_with_reference(name):
    both(HARD_CASES[name], camera(torch.float32), background=(0.5, 0.25, 1.0))


@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_agree_in_float64(name):
    g = HARD_CASES[name].to(dtype=torch.float64)
    out = both(g, camera(), atol=ATOL_F64, background=(0.5, 0.25, 1.0))
    assert out.rgb.dtype == torch.float64


@pytest.mark.parametrize("factor", MAGNITUDES)
@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_agree_at_extreme_magnitudes_in_float64(name, factor):
    """Means, quaternions, scales or SH far beyond float32's range (1e300 times), at its edge
    (1e30) or below its subnormals (1e-300): both backends finite and equal."""
    for field in SCALABLE_FIELDS:
        g = scaled(HARD_CASES[name], field, factor)
        try:
            both(g, camera(), atol=ATOL_F64, rtol=ATOL_F64, background=(0.5, 0.25, 1.0))
        except AssertionError as e:
            raise AssertionError(f"{field} x {factor:g}: {e}") from None


@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_agree_at_float32_extremes(name):
    """Float32 values near the top of its range: colours and depths must not overflow in the
    float32 stages of either backend."""
    for field in SCALABLE_FIELDS:
        for factor in (1e30, 1e-30):
            try:
                both(scaled(HARD_CASES[name], field, factor, torch.float32), camera(torch.float32), rtol=ATOL)
            except AssertionError as e:
                raise AssertionError(f"{field} x {factor:g}: {e}") from None


def test_float32_colour_and_depth_beyond_its_range_stay_finite():
    """SH of 3e38 sum to a colour above float32's largest value, and a centre 5e38 m away has
    a depth above it: the colour is clamped at MAX_COLOR, the far splat culled."""
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 3e38]]), quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
        scales=torch.full((2, 3), 0.3), opacities=torch.tensor([0.5, 0.9]), sh=torch.full((2, 9, 3), 3e38),
    )  # fmt: skip
    c2w = torch.eye(4)
    c2w[2, 3] = -2e38
    out = both(g, camera(torch.float32), rtol=ATOL)
    centre = out.alpha.argmax()
    assert out.rgb[0, 0].flatten()[centre] / out.alpha.flatten()[centre] == pytest.approx(MAX_COLOR, rel=1e-5)
    assert (both(g[1:], camera(c2w=c2w)).alpha == 0).all()


def test_float64_file_beyond_float32_range_renders_the_same_in_both_backends(tmp_path):
    """SH of 1e39 and quaternions of 1e300 from a float64 safetensors file: the fast backend
    used to return NaN for the first and another orientation for the second."""
    g = random_scene(n=60, seed=11, dtype=torch.float64, sh_degree=2)
    g.sh[:20] *= 1e39
    g.quats[20:40] *= 1e300
    g.save(tmp_path / "far.safetensors")
    loaded, _ = Gaussians.load(tmp_path / "far.safetensors")
    out = both(loaded, camera(), atol=ATOL_F64, rtol=ATOL_F64)
    assert out.rgb.max() > 1e30  # colours are clamped at MAX_COLOR, not lost
    unit = Gaussians(**{**g.tensors(), "quats": g.quats / g.quats.abs().amax(-1, keepdim=True)})
    unit.sh[:20] = 0
    plain = Gaussians(**{**g.tensors(), "sh": unit.sh})
    torch.testing.assert_close(render(plain, camera(), backend="fast").alpha,
                               render(unit, camera(), backend="fast").alpha)  # fmt: skip


def test_camera_far_from_the_origin_in_float64():
    """A float64 camera 1e300 m from the scene sees nothing, in both backends."""
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([1e300, -1e300, 1e300], dtype=torch.float64)
    out = both(random_scene(n=50, seed=12, dtype=torch.float64), camera(c2w=c2w), atol=ATOL_F64)
    assert (out.alpha == 0).all()


def test_hard_cases_all_at_once():
    """All hard cases in one scene (mixed with random splats), from a rotated camera."""
    g = Gaussians.cat([*HARD_CASES.values(), random_scene(n=100, seed=9, sh_degree=1)])
    both(g, camera(c2w=look_at((0.3, 0.2, -0.5), (0.0, 0.0, 2.0), up=(0.0, -1.0, 0.0))))


def test_compiled_code_is_cached_for_new_processes():
    """A fresh process (a new dataloader worker) loads the compiled kernels from the disk
    cache instead of compiling them."""
    render(random_scene(n=20), camera(), backend="fast")  # make sure this process compiled
    script = textwrap.dedent("""
        import torch
        from gensplat_transforms import Cameras, Gaussians, render
        from gensplat_transforms.rendering import fast
        g = Gaussians(torch.tensor([[0.0, 0.0, 2.0]]), torch.tensor([[1.0, 0, 0, 0]]),
                      torch.full((1, 3), 0.1), torch.tensor([0.5]), torch.zeros(1, 16, 3))
        cam = Cameras.from_intrinsics(40.0, 44.0, 22.8, 18.8, torch.eye(4, dtype=torch.float64), 45, 38)
        render(g, cam, backend="fast")
        kernels = [fast._project_serial, fast._bin_serial, fast._raster_serial]
        print(sum(len(k.stats.cache_misses) for k in kernels), sum(len(k.stats.cache_hits) for k in kernels))
    """)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                          timeout=120, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    misses, hits = map(int, done.stdout.split())
    assert misses == 0 and hits == 3


def test_code_compiled_for_avx2_only_renders_the_same(tmp_path):
    """The kernels compiled without AVX-512 (what an AVX2-only CPU gets: 8 float32 lanes, not
    16) give the images of this process's code on every hard case and a random scene, on
    one thread and two. Where the CPU has no AVX-512, both compilations are the same."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
    from machine import avx2_features

    g = Gaussians.cat([*HARD_CASES.values(), random_scene(n=400, seed=12, sh_degree=3)])
    cam = camera(c2w=look_at((0.3, 0.2, -0.5), (0.0, 0.0, 2.0), up=(0.0, -1.0, 0.0)))
    torch.save({"g": g.tensors(), "K": cam.K, "c2w": cam.c2w}, tmp_path / "scene.pt")
    script = textwrap.dedent(f"""
        import torch
        from gensplat_transforms import Cameras, Gaussians, render
        s = torch.load({str(tmp_path / "scene.pt")!r})
        g, cam = Gaussians(**s["g"]), Cameras(s["K"], s["c2w"], {W}, {H})
        outs = [render(g, cam, backend="fast", threads=t) for t in (1, 2)]
        torch.save([(o.rgb, o.depth, o.alpha) for o in outs], {str(tmp_path / "avx2.pt")!r})
    """)
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_DISABLE_JIT"}
    env |= {"NUMBA_CPU_FEATURES": avx2_features(), "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env,
                          timeout=600, check=False)  # fmt: skip
    assert done.returncode == 0, done.stderr
    for threads, (rgb, depth, alpha) in zip((1, 2), torch.load(tmp_path / "avx2.pt")):
        native = render(g, cam, backend="fast", threads=threads)
        for name, a, b in (("rgb", rgb, native.rgb), ("depth", depth, native.depth), ("alpha", alpha, native.alpha)):
            assert torch.allclose(a, b, rtol=1e-6, atol=1e-6), (threads, name, (a - b).abs().max())


@pytest.mark.parametrize("threads", [1, 2])
def test_tile_lists_hold_every_touched_tile_in_depth_order(threads):
    """Binning against a plain loop: boxes of one tile, several tiles, on the image's last
    (partial) tiles, in a shuffled depth order."""
    rng = np.random.default_rng(threads)
    ntx, nty = -(-W // fast.TILE), -(-H // fast.TILE)
    x0, y0 = rng.integers(0, W, 500), rng.integers(0, H, 500)
    span = rng.choice([0, 3, 20, 40], (2, 500))
    boxes = np.stack([x0, y0, np.minimum(x0 + span[0], W - 1), np.minimum(y0 + span[1], H - 1)], 1).astype(np.int32)
    order = rng.permutation(500).astype(np.int32)
    want = [[] for _ in range(ntx * nty)]
    for i in order:
        for ty in range(boxes[i, 1] // fast.TILE, boxes[i, 3] // fast.TILE + 1):
            for tx in range(boxes[i, 0] // fast.TILE, boxes[i, 2] // fast.TILE + 1):
                want[ty * ntx + tx].append(i)
    if threads == 1:
        start, ids = fast._bin_serial(order, boxes, ntx, nty)
    else:
        start, ids = fast._bin_parallel(order, boxes, ntx, nty, threads)
    assert [ids[start[t] : start[t + 1]].tolist() for t in range(ntx * nty)] == want


def test_parallel_projection_joins_its_chunks_like_the_serial_one():
    """Chunks of Gaussians project independently and their splats are moved together: with
    chunks that see nothing, all, or part of the scene, the same records, boxes and order."""
    g = random_scene(n=900, seed=13, sh_degree=2)
    means = g.means.clone()
    means[:300, 2] = -1.0  # the first chunk of three is behind the camera
    cam = camera()
    W_, H_ = cam.width, cam.height
    fx, fy, cx, cy = 40.0, 44.0, W / 2 + 0.3, H / 2 - 0.2
    lims = fast.fov_limits(W_, H_, fx, fy, cx, cy)
    cam_array = np.array([*torch.eye(4, dtype=torch.float64)[:3].reshape(-1).tolist(), fx, fy, cx, cy, *lims, 0, 0, 0])
    args = (means.numpy(), g.quats.numpy(), g.scales.numpy(), g.opacities.numpy(), g.sh.numpy(), 2, cam_array,
            0.01, np.float32(fast.ALPHA_MIN), W_, H_)  # fmt: skip
    serial = fast._project_serial(*args)
    assert 0 < len(serial[0]) < 600
    for nchunks in (1, 3, 7):
        for got, want in zip(fast._project_parallel(*args, nchunks), serial):
            np.testing.assert_array_equal(got, want)


@pytest.mark.parametrize("seed", [0, 1])
def test_sharp_footprint_options_agree_with_reference(seed):
    """A smaller dilation and saturated splats (the RGB-D discs' footprint) in both backends."""
    g = random_scene(seed=seed, scale=0.03)
    out = both(g, camera(torch.float32), dilation=0.05, saturation=3.0)
    default = render(g, camera(torch.float32), backend="fast")
    assert (out.alpha - default.alpha).abs().max() > 0.05  # the options change the image


@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_agree_with_sharp_footprints(name):
    both(HARD_CASES[name], camera(torch.float32), background=(0.5, 0.25, 1.0), dilation=0.01, saturation=50.0)


def test_saturation_makes_flat_topped_splats():
    """A disc of sigma 0.3 px seen face on, centred between two pixel centres: saturated on
    both, and 1.5 px away nearly nothing, where the unsaturated splat is 0.73 and 0.056."""
    cam = Cameras.from_intrinsics(100.0, 100.0, 8.0, 8.0, torch.eye(4), 16, 16)
    g = Gaussians(torch.tensor([[0.0, -0.005, 1.0]]), torch.tensor([[1.0, 0, 0, 0]]),  # at u = 8.0, v = 7.5
                  torch.tensor([[0.003, 0.003, 1e-5]]), torch.ones(1), torch.ones(1, 1, 3))  # fmt: skip
    for backend in ("reference", "fast"):
        plain = render(g, cam, backend=backend).alpha[0, 0]  # sigma^2 = 0.09 + 0.3
        sharp = render(g, cam, backend=backend, dilation=0.05, saturation=3.0).alpha[0, 0]  # 0.09 + 0.05
        for col, distance in ((7, 0.5), (8, 0.5), (9, 1.5)):
            assert plain[7, col] == pytest.approx(math.exp(-0.5 * distance**2 / 0.39), rel=1e-3)
            a = min(0.99, 3 * math.exp(-0.5 * distance**2 / 0.14))
            assert sharp[7, col] == pytest.approx(a if a >= 1 / 255 else 0.0, rel=1e-3)  # below 1/255: skipped
        assert sharp[7, 7] == sharp[7, 8] == pytest.approx(0.99) and sharp[7, 9] == 0


@pytest.mark.parametrize("options, message", [
    ({"dilation": 0.0}, "dilation"), ({"dilation": float("nan")}, "dilation"), ({"dilation": -1.0}, "dilation"),
    ({"saturation": 0.5}, "saturation"), ({"saturation": float("inf")}, "saturation"),
])  # fmt: skip
def test_footprint_options_are_checked(options, message):
    for backend in ("reference", "fast"):
        with pytest.raises(ValueError, match=message):
            render(random_scene(n=3), camera(), backend=backend, **options)
