"""The differentiable reference renderer: analytic footprint, brute-force agreement,
gradients, and hard cases."""

import math
from functools import partial

import pytest
import torch
from dense_renderer import dense_render
from hard_cases import HARD_CASES, MAGNITUDES, SCALABLE_FIELDS, scaled

from gensplat_transforms import Cameras, Gaussians
from gensplat_transforms.core.sh import C0, eval_sh
from gensplat_transforms.rendering import auto_backend
from gensplat_transforms.rendering import render as render_any

render = partial(render_any, backend="reference")  # the backend these tests cover

W, H = 40, 32


def camera(dtype=torch.float64, c2w=None, f=40.0):
    c2w = torch.eye(4, dtype=dtype) if c2w is None else c2w
    return Cameras.from_intrinsics(f, f * 1.1, W / 2 + 0.3, H / 2 - 0.2, c2w, W, H)


def random_scene(n=40, seed=0, dtype=torch.float32, sh_degree=2):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * torch.tensor([0.5, 0.4, 0.3]) + torch.tensor([0, 0, 2.0])
    return Gaussians(
        means=means.to(dtype),
        quats=torch.randn(n, 4, generator=g).to(dtype),
        scales=(torch.rand(n, 3, generator=g) * 0.08 + 0.005).to(dtype),
        opacities=(torch.rand(n, generator=g) * 0.95 + 0.05).to(dtype),
        sh=(torch.randn(n, (sh_degree + 1) ** 2, 3, generator=g) * 0.4).to(dtype),
    )


def dense_of(g: Gaussians, cam: Cameras, background=(0.0, 0.0, 0.0)):
    colors = eval_sh(g.sh.double(), g.means.double() - cam.centers[0].double())
    return dense_render(g.means, g.quats, g.scales, g.opacities, colors, cam.K[0], cam.c2w[0], W, H, background)


def assert_finite(out):
    for name in ("rgb", "depth", "alpha"):
        t = getattr(out, name)
        assert torch.isfinite(t).all(), f"{name} has non-finite values"


# ---------------------------------------------------------------------------- analytic


def test_single_gaussian_matches_analytic_footprint():
    f, z, s, o = 40.0, 2.0, 0.03, 0.8
    cam = Cameras.from_intrinsics(f, f, W / 2, H / 2, torch.eye(4, dtype=torch.float64), W, H)
    rgb_dc = torch.tensor([0.9, 0.2, 0.4])
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, z]]), quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.full((1, 3), s), opacities=torch.tensor([o]), sh=((rgb_dc - 0.5) / C0)[None, None],
    )  # fmt: skip
    out = render(g, cam, background=(0.1, 0.1, 0.1))
    sigma2 = (f * s / z) ** 2 + 0.3  # EWA: projected variance plus the 0.3 px^2 dilation
    v, u = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    r2 = (u - W / 2) ** 2 + (v - H / 2) ** 2
    q = r2 / sigma2
    alpha = o * torch.exp(-0.5 * q)
    alpha = torch.where((q <= 9) & (alpha >= 1 / 255), alpha, torch.zeros_like(alpha))
    torch.testing.assert_close(out.alpha[0, 0], alpha, atol=1e-5, rtol=1e-5)
    expected = rgb_dc[:, None, None] * alpha + 0.1 * (1 - alpha)
    torch.testing.assert_close(out.rgb[0], expected, atol=1e-5, rtol=1e-5)
    assert torch.allclose(out.depth[0, 0][alpha > 0], torch.tensor(z))
    assert (out.depth[0, 0][alpha == 0] == 0).all()


def test_field_of_view_clamp_is_that_of_3dgs_and_gsplat():
    """Off-image centres use the Jacobian at x/z clamped to (W - cx) / fx + 0.3 tan(fov_x / 2)."""
    from gensplat_transforms.rendering.projection import project

    f, z, s = 40.0, 2.0, 1.0
    cam = Cameras.from_intrinsics(f, f, W / 2, H / 2, torch.eye(4, dtype=torch.float64), W, H)
    x = z * W / f  # x/z = W / f, 20 px right of the image's edge: beyond the clamp at 0.65 W / f
    g = Gaussians(
        means=torch.tensor([[x, 0.0, z]]), quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.full((1, 3), s), opacities=torch.tensor([1.0]), sh=torch.zeros(1, 1, 3),
    )  # fmt: skip
    p = project(g, cam, out_dtype=torch.float64)
    assert len(p) == 1  # wide enough to reach into the image
    tx = (W - W / 2) / f + 0.3 * 0.5 * W / f
    J = torch.tensor([[f / z, 0, -f * tx / z], [0, f / z, 0]], dtype=torch.float64)
    cov = s**2 * J @ J.T + 0.3 * torch.eye(2, dtype=torch.float64)
    inv = torch.linalg.inv(cov)
    torch.testing.assert_close(p.conics[0], torch.stack([inv[0, 0], inv[0, 1], inv[1, 1]]))


# ---------------------------------------------------------------------------- brute force


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sh_degree", [0, 3])
def test_agrees_with_dense_renderer(seed, sh_degree):
    g = random_scene(seed=seed, sh_degree=sh_degree, dtype=torch.float64)
    cam = camera()
    out = render(g, cam, background=(0.2, 0.5, 0.7))
    rgb, depth, alpha = dense_of(g, cam, (0.2, 0.5, 0.7))
    assert alpha.max() > 0.5, "scene should cover part of the image"
    torch.testing.assert_close(out.rgb[0], rgb, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.alpha[0, 0], alpha, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.depth[0, 0], depth, atol=1e-8, rtol=1e-8)


def test_agrees_with_dense_renderer_from_rotated_camera():
    from gensplat_transforms import look_at

    g = random_scene(n=60, seed=5, dtype=torch.float64)
    cam = camera(c2w=look_at([1.2, -0.6, 0.3], [0.0, 0.0, 2.0], up=[0, -1, 0]))
    out = render(g, cam)
    rgb, depth, alpha = dense_of(g, cam)
    assert alpha.max() > 0.5
    torch.testing.assert_close(out.rgb[0], rgb, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.depth[0, 0], depth, atol=1e-8, rtol=1e-8)


def test_opaque_stack_stops_at_transmittance_floor():
    # 6 stacked splats of alpha 0.95: T would reach 1.6e-8; the stop rule keeps T >= 1e-4
    # (T = 0.05^3 = 1.25e-4 after three, the fourth would give 6e-6 and is not taken).
    n = 6
    g = Gaussians(
        means=torch.tensor([[0.0, 0.0, 2.0]]).repeat(n, 1) + torch.linspace(0, 0.1, n)[:, None] * torch.tensor([0, 0, 1.0]),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), scales=torch.full((n, 3), 0.2),
        opacities=torch.full((n,), 0.95), sh=torch.randn(n, 1, 3),
    )  # fmt: skip
    # principal point on the centre of pixel (H//2, W//2), so that pixel sees alpha = 0.95
    cam = Cameras.from_intrinsics(40.0, 40.0, W // 2 + 0.5, H // 2 + 0.5, torch.eye(4), W, H)
    out = render(g, cam)
    ref = dense_of(g, cam)
    torch.testing.assert_close(out.rgb[0].double(), ref[0], atol=1e-5, rtol=1e-5)
    centre_t = 1 - out.alpha[0, 0, H // 2, W // 2]
    assert abs(centre_t - 0.05**3) < 1e-7


def test_chunking_does_not_change_the_image():
    g = random_scene(n=80, seed=3)
    cam = camera(torch.float32)
    a = render(g, cam)
    b = render(g, cam, max_pairs=200)  # many chunks, transmittance carried across them
    torch.testing.assert_close(a.rgb, b.rgb, atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(a.depth, b.depth, atol=1e-5, rtol=1e-5)


def test_batch_of_cameras_and_output_shapes():
    g = random_scene()
    cams = Cameras.cat([camera(torch.float32), camera(torch.float32, f=30.0)])
    out = render(g, cams, return_depth=False)
    assert out.rgb.shape == (2, 3, H, W) and out.alpha.shape == (2, 1, H, W) and out.depth is None
    assert out.rgb.dtype == torch.float32
    single = render(g, cams[1])
    torch.testing.assert_close(out.rgb[1:], single.rgb)


# ---------------------------------------------------------------------------- gradients


def test_gradcheck_float64_tiny_scene():
    g = random_scene(n=3, seed=7, dtype=torch.float64, sh_degree=1)
    W0, H0 = 10, 8
    K = torch.tensor([[10.0, 0, 5.0], [0, 10.0, 4.0], [0, 0, 1]], dtype=torch.float64)
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, 3] = torch.tensor([0.02, -0.01, 0.03])
    inputs = [t.clone().requires_grad_(True) for t in (*g.tensors().values(), c2w)]

    def fn(means, quats, scales, opacities, sh, c2w):
        cams = Cameras(K, c2w, W0, H0)
        gs = Gaussians(means, quats, scales, opacities, sh)
        out = render(gs, cams, background=(0.3, 0.3, 0.3))
        return out.rgb, out.depth, out.alpha

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-5, rtol=1e-4)


def test_gradients_reach_every_input_including_camera_pose():
    g = random_scene(n=30, seed=1)
    params = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    c2w = torch.eye(4, dtype=torch.float32).requires_grad_(True)
    cam = Cameras.from_intrinsics(40.0, 40.0, W / 2, H / 2, c2w, W, H)
    out = render(Gaussians(**params), cam)
    (out.rgb.square().sum() + out.depth.sum() + out.alpha.sum()).backward()
    for name, p in {**params, "c2w": c2w}.items():
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, f"no gradient reaches {name}"


# ---------------------------------------------------------------------------- hard cases


#: the hard cases of which nothing reaches the image
INVISIBLE = ("behind_camera", "at_camera_centre", "on_near_plane", "zero_opacity", "below_alpha_threshold", "empty_scene",
             "far_outside_image")


@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_stay_finite_with_finite_gradients(name):
    g = HARD_CASES[name]
    params = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
    out = render(Gaussians(**params), camera(torch.float32), background=(0.5, 0.5, 0.5))
    assert_finite(out)
    assert ((out.alpha >= 0) & (out.alpha <= 1)).all()
    if name in INVISIBLE:  # background only (test_invisible_cases_render_only_background): no gradient to check
        return
    (out.rgb.sum() + out.depth.sum() + out.alpha.sum()).backward()
    for k, p in params.items():
        assert p.grad is not None and torch.isfinite(p.grad).all(), f"{name}: missing or non-finite grad for {k}"


@pytest.mark.parametrize("factor", MAGNITUDES)
@pytest.mark.parametrize("name", sorted(HARD_CASES))
def test_hard_cases_at_extreme_magnitudes_stay_finite_with_finite_gradients(name, factor):
    """float64 means, quaternions, scales or SH at 1e30, 1e300 or 1e-300 times their value."""
    for field in SCALABLE_FIELDS:
        g = scaled(HARD_CASES[name], field, factor)
        params = {k: v.clone().requires_grad_(True) for k, v in g.tensors().items()}
        out = render(Gaussians(**params), camera(), background=(0.5, 0.5, 0.5))
        assert_finite(out)
        loss = out.rgb.sum() + out.depth.sum() + out.alpha.sum()
        if loss.requires_grad:
            loss.backward()
            for k, p in params.items():
                assert p.grad is None or torch.isfinite(p.grad).all(), f"{field} x {factor:g}: grad of {k}"


@pytest.mark.parametrize("name", INVISIBLE)
def test_invisible_cases_render_only_background(name):
    out = render(HARD_CASES[name], camera(torch.float32), background=(0.5, 0.25, 1.0))
    assert (out.alpha == 0).all()
    torch.testing.assert_close(out.rgb[0], torch.tensor([0.5, 0.25, 1.0])[:, None, None].expand(3, H, W))


@pytest.mark.parametrize("name", ["centre_outside_image", "on_image_border", "zero_scale", "tiny_scale",
                                  "zero_quaternion", "just_past_near_plane"])
def test_hard_cases_agree_with_dense_renderer(name):
    g = HARD_CASES[name].to(dtype=torch.float64)
    cam = camera()
    out = render(g, cam)
    rgb, _, alpha = dense_of(g, cam)
    torch.testing.assert_close(out.rgb[0], rgb, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out.alpha[0, 0], alpha, atol=1e-9, rtol=1e-9)


def test_huge_gaussian_covers_whole_image_with_its_opacity():
    out = render(HARD_CASES["huge_scale"], camera(torch.float32))
    torch.testing.assert_close(out.alpha, torch.full_like(out.alpha, 0.9))


def test_unnormalised_quaternion_equals_normalised():
    g = HARD_CASES["unnormalised_quaternion"]
    unit = Gaussians(**{**g.tensors(), "quats": g.quats / g.quats.norm(dim=-1, keepdim=True)})
    torch.testing.assert_close(render(g, camera()).rgb, render(unit, camera()).rgb)


def test_zero_quaternion_is_identity_rotation():
    g = HARD_CASES["zero_quaternion"]
    ident = Gaussians(**{**g.tensors(), "quats": torch.tensor([[1.0, 0, 0, 0]])})
    torch.testing.assert_close(render(g, camera()).rgb, render(ident, camera()).rgb)


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_inputs_render_in_float32(dtype):
    g = random_scene(n=60, seed=2)
    half = g.to(dtype=dtype)
    out = render(half, camera(torch.float32))
    assert out.rgb.dtype == torch.float32
    assert_finite(out)
    ref = render(half.to(dtype=torch.float32), camera(torch.float32))  # same rounded values
    torch.testing.assert_close(out.rgb, ref.rgb, atol=1e-5, rtol=1e-5)
    params = {k: v.clone().requires_grad_(True) for k, v in half.tensors().items()}
    render(Gaussians(**params), camera(torch.float32)).rgb.sum().backward()
    assert all(torch.isfinite(p.grad.float()).all() for p in params.values())


@pytest.mark.parametrize("field", ["means", "quats", "scales", "opacities", "sh"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_inputs_raise_naming_the_field(field, bad):
    g = random_scene(n=5)
    t = getattr(g, field)
    t.view(-1)[0] = bad  # corrupt after construction: render re-checks
    with pytest.raises(ValueError, match=field):
        render(g, camera(torch.float32))


def test_bad_arguments_raise():
    g = random_scene(n=5)
    with pytest.raises(ValueError, match="backend"):
        render(g, camera(), backend="nope")
    with pytest.raises(ValueError, match="near"):
        render(g, camera(), near=0.0)
    with pytest.raises(ValueError, match="background"):
        render(g, camera(), background=(0.0, math.nan, 0.0))
    c2w = torch.eye(4)
    c2w[0, 3] = math.inf
    with pytest.raises(ValueError, match="c2w"):
        camera(c2w=c2w)


# ---------------------------------------------------------------------------- backend "auto"
def test_auto_backend_is_fast_without_grad_and_reference_with_grad():
    g = random_scene()
    cam = camera(torch.float32)
    assert auto_backend(g, cam) == "fast"  # CPU Gaussians, even with gsplat installed
    torch.testing.assert_close(render_any(g, cam).rgb, render_any(g, cam, backend="fast").rgb,
                               rtol=0, atol=0)  # fmt: skip
    for field in ("means", "sh"):
        learnt = Gaussians(**{**g.tensors(), field: getattr(g, field).clone().requires_grad_()})
        assert auto_backend(learnt, cam) == "reference"
        out = render_any(learnt, cam)
        assert out.rgb.requires_grad
        torch.testing.assert_close(out.rgb, render(learnt, cam).rgb, rtol=0, atol=0)
        with torch.no_grad():  # no graph is recorded: the fast renderer does
            assert auto_backend(learnt, cam) == "fast"
    background = torch.tensor([0.2, 0.3, 0.4], requires_grad=True)
    assert auto_backend(g, cam, background) == "reference"
    moving = Cameras(cam.K, cam.c2w.clone().requires_grad_(), W, H)
    assert auto_backend(g, moving) == "reference"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_auto_backend_on_cuda_is_gsplat_when_installed():
    import importlib.util

    g, cam = random_scene().to("cuda"), camera(torch.float32)
    expected = "gsplat" if importlib.util.find_spec("gsplat") else "fast"
    assert auto_backend(g, cam) == expected
    torch.testing.assert_close(render_any(g, cam).rgb, render_any(g, cam, backend=expected).rgb,
                               rtol=0, atol=0)  # fmt: skip
