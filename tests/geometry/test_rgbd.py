"""RGB-D reconstruction: pixel-aligned Gaussians reproduce their source views."""

import re
from dataclasses import replace

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from gensplat_transforms import Cameras, PaperSampler, pivot_point, render
from gensplat_transforms.core.metrics import psnr
from gensplat_transforms.core.rotations import quat_to_rotmat
from gensplat_transforms.core.views import Reconstruction, pixel_rays, preferred_means, source_rays
from gensplat_transforms.data.scenes import LABEL_TABLE, TabletopScene, default_cameras
from gensplat_transforms.geometry import RGBDReconstructor, Views
from gensplat_transforms.geometry.rgbd import RGBDConfig, disc_identity

SIZE = 96


@pytest.fixture(scope="module")
def scene_views():
    scene = TabletopScene(0)
    cams = default_cameras(SIZE, SIZE)
    images, depths = scene.render(cams)
    return scene, cams, images, depths


def depth_edges(depth: torch.Tensor, rel_jump=0.05, margin=2) -> torch.Tensor:
    """(V,1,H,W) bool: pixels within ``margin`` px of a relative depth jump > ``rel_jump``."""
    hi = F.max_pool2d(depth, 3, 1, 1)
    lo = -F.max_pool2d(-depth, 3, 1, 1)
    edge = ((hi - lo) / depth > rel_jump).float()
    return F.max_pool2d(edge, 2 * margin + 1, 1, margin) > 0


def test_single_view_reproduces_its_source(scene_views):
    _, cams, images, depths = scene_views
    cam, img, dep = cams[0], images[:1], depths[:1]
    g = RGBDReconstructor().reconstruct(Views(img, cam, dep)).gaussians
    assert len(g) == SIZE * SIZE  # every pixel has valid depth in this scene
    out = render(g, cam)
    # Coverage: every pixel sees its own splat at alpha 0.99 (opacity 1, clamped).
    assert out.alpha.min() >= 0.99 - 1e-6
    # Bound: away from depth edges a splat (variance k^2 + 0.3 = 0.46 px^2 in the source
    # camera) mixes a pixel with its neighbours no more than resampling the image half a
    # pixel off diagonally does, so the render must be at least that close to the source.
    interior = ~depth_edges(dep)
    half_px = 0.25 * (img[..., :-1, :-1] + img[..., 1:, :-1] + img[..., :-1, 1:] + img[..., 1:, 1:])
    m = interior[..., :-1, :-1]
    bound = psnr(half_px, img[..., :-1, :-1], m)
    assert psnr(out.rgb[..., :-1, :-1], img[..., :-1, :-1], m) >= bound
    # At silhouettes the front splats overhang by about a pixel; the whole image stays close.
    assert psnr(out.rgb, img) >= 28.0
    rel = ((out.depth - dep).abs() / dep)[interior]
    assert rel.median() < 0.01


def test_fused_views_cover_every_view_with_correct_depth(scene_views):
    _, cams, images, depths = scene_views
    recon = RGBDReconstructor().reconstruct(Views(images, cams, depths))
    assert len(recon.gaussians) == 3 * SIZE * SIZE
    out = render(recon.gaussians, recon.cameras)
    assert out.alpha.min() >= 0.99 - 1e-6
    interior = ~depth_edges(depths)
    rel = ((out.depth - depths).abs() / depths)[interior]
    assert rel.median() < 0.01
    for v in range(3):
        assert psnr(out.rgb[v], images[v]) >= 26.0


def test_novel_view_beats_the_unchanged_image_at_large_level(scene_views):
    scene, cams, images, depths = scene_views
    g = RGBDReconstructor().reconstruct(Views(images[:2], cams[:2], depths[:2])).gaussians
    pivot = pivot_point(cams.c2w[0], cams.c2w[1])
    p = PaperSampler("large", seed=0).sample(0)
    target = cams[0].with_c2w(p.apply(cams.c2w[:1], pivot))
    truth, _ = scene.render(target)
    out = render(g, target)
    seen = out.alpha > 0.5
    assert seen.float().mean() > 0.85  # the rest was never seen by the sources
    # The unchanged source image is the baseline a novel view must beat (measured: 26.8 vs
    # 19.5 dB at this size).
    assert psnr(out.rgb, truth, seen) > psnr(images[:1], truth, seen) + 5.0


def test_splats_lie_flat_in_the_surface(scene_views):
    scene, cams, images, depths = scene_views
    cam = cams[0]
    g = RGBDReconstructor().reconstruct(Views(images[:1], cam, depths[:1])).gaussians
    on_table = (scene.labels(cam) == LABEL_TABLE).reshape(-1)
    R = quat_to_rotmat(g.quats[on_table])
    thin_axis = R.gather(2, g.scales[on_table].argmin(-1)[:, None, None].expand(-1, 3, 1))[..., 0]
    # the table's normal is world z: the thinnest axis of a table splat points along it
    assert thin_axis[:, 2].abs().median() > 0.99
    s = g.scales[on_table].sort(-1).values
    ratio = s[:, 0] / s[:, 1]  # thickness over the smaller in-plane size (t = 0.1 nominal)
    assert ratio.median() < 0.15 and ratio.max() < 0.5


def test_invalid_depth_pixels_are_skipped_and_stride_thins(scene_views):
    _, cams, images, depths = scene_views
    dep = depths[:1].clone()
    dep[..., :10, :] = 0.0
    dep[..., 10:20, :] = float("nan")
    dep[..., 20:30, :] = -1.0
    g = RGBDReconstructor().reconstruct(Views(images[:1], cams[0], dep)).gaussians
    assert len(g) == (SIZE - 30) * SIZE
    g2 = RGBDReconstructor(stride=2).reconstruct(Views(images[:1], cams[0], depths[:1])).gaussians
    assert len(g2) == (SIZE // 2) ** 2
    assert RGBDReconstructor(max_depth=0.0).reconstruct(Views(images[:1], cams[0], depths[:1])).gaussians.means.shape[0] == 0


def test_identity_tracks_what_the_cache_stores_not_the_disc_shape():
    """The stored depth depends on max_depth; the disc shape is how workers build discs from it."""
    assert RGBDReconstructor().identity() == RGBDReconstructor().identity()
    assert RGBDReconstructor().identity() != RGBDReconstructor(max_depth=5.0).identity()
    assert RGBDReconstructor().identity().startswith("rgbd-")
    shapes = [RGBDReconstructor(**{k: v}) for k, v in [("sigma_px", 0.45), ("thickness", 0.3), ("max_stretch", 2.0),
              ("edge_scale", 1.0), ("opacity", 0.8), ("sh_degree", 1), ("stride", 2), ("cover", 0.5)]]  # fmt: skip
    assert {r.identity() for r in shapes} == {RGBDReconstructor().identity()} == {"rgbd-b4a28c8cc49722ec"}
    assert disc_identity(RGBDConfig(sigma_px=0.45)) == disc_identity(RGBDConfig()) != disc_identity(RGBDConfig(max_depth=2))


def test_bad_inputs_raise_clear_errors(scene_views):
    _, cams, images, depths = scene_views
    with pytest.raises(ValueError, match="depths"):
        RGBDReconstructor().reconstruct(Views(images, cams))
    with pytest.raises(ValueError, match="cameras"):
        RGBDReconstructor().reconstruct(Views(images, None, depths))
    with pytest.raises(ValueError, match="Views.images"):
        Views(images[:, :2], cams, depths)
    for value in (float("nan"), float("inf"), -float("inf")):
        for dtype in (torch.float32, torch.float16, torch.bfloat16):
            bad = images.to(dtype, copy=True)
            bad[1, 2, 5, 7] = value
            with pytest.raises(ValueError, match="Views.images: contains NaN or Inf"):
                Views(bad, cams, depths)
    with pytest.raises(ValueError, match="Views.cameras"):
        Views(images, cams[:2], depths)
    with pytest.raises(ValueError, match="Views.depths"):
        Views(images, cams, depths[..., :-1])
    with pytest.raises(ValueError, match="sigma_px"):
        RGBDReconstructor(sigma_px=0.0)


@pytest.mark.parametrize("field, value, what", [
    ("sigma_px", "0.3", "a number > 0"), ("sigma_px", float("nan"), "a number > 0"), ("thickness", -0.1, ">= 0"),
    ("edge_scale", 0.0, "in (0, 1]"), ("opacity", True, "in [0, 1]"), ("sh_degree", 1.5, "whole number"),
    ("max_depth", -1.0, "None or a number >= 0"), ("max_depth", "2", "None or a number >= 0"),
    ("stride", 2.0, "whole number >= 1"), ("fill_depth_px", -1, "whole number >= 0"),
    ("fill_depth_px", True, "whole number >= 0"), ("dilation", float("inf"), "> 0"), ("saturation", 0.5, ">= 1"),
    ("view_preference", None, "in [0, 1]"), ("cover", 0.0, "in (0, 1]"), ("soften_noise", "false", "True or False"),
])  # fmt: skip
def test_disc_settings_refuse_what_they_cannot_use_and_say_what_they_need(field, value, what):
    """Wrong types (a string from a hand-edited settings file, a bool) and values out of range are
    refused with the field, what it must be and the value given, never a TypeError from deep inside."""
    with pytest.raises(ValueError, match=re.escape(f"RGBDConfig.{field} must be") + ".*" + re.escape(what)):
        RGBDConfig(**{field: value})
    assert RGBDConfig(sigma_px=np.float32(0.3), stride=np.int64(2), max_depth=3).stride == 2  # NumPy numbers are numbers


@pytest.mark.parametrize("fast", [True, False])
def test_sentinel_depths_mark_pixels_without_depth(scene_views, fast):
    """Depths of 1e7 m and more (sensor sentinels) are invalid like 0, negative, NaN and Inf:
    those pixels get no Gaussian, instead of Gaussians that overflow float32 (which used to
    raise an error about Gaussians.scales)."""
    _, cams, images, depths = scene_views
    bad = depths[:1].clone()
    sentinels = [1e7, 1e19, 3.4e38, float("inf"), float("nan"), -1.0, 0.0]
    for i, value in enumerate(sentinels):
        bad[0, 0, i, :] = value
    g = RGBDReconstructor(fast=fast).reconstruct(Views(images[:1], cams[0], bad)).gaussians
    assert len(g) == SIZE * (SIZE - len(sentinels))
    assert g.means[:, 2].max() < 10 and g.scales.max() < 1
    g.check(force=True)  # valid, although the compiled path marks its output checked without the scan


def test_a_camera_with_zero_focal_length_is_refused_naming_the_camera(scene_views):
    _, cams, images, depths = scene_views
    K = cams.K.clone()
    K[0, 0, 0] = 0.0
    with pytest.raises(ValueError, match=r"Cameras.K: focal lengths must be > 0"):
        Views(images, Cameras(K, cams.c2w, SIZE, SIZE), depths)


@pytest.mark.parametrize("overrides", [{}, {"stride": 2}, {"max_depth": 1.2, "edge_scale": 0.5}])
def test_compiled_discs_match_the_pytorch_rule(scene_views, overrides):
    """The compiled disc builder (default) against the PyTorch rule: same pixels, centres,
    colours and covariances (quaternions may differ by sign or by an in-plane half-turn)."""
    from gensplat_transforms.core.rotations import covariance_3d

    _, cams, images, depths = scene_views
    depths = depths.clone()
    depths[0, 0, 10:20, 30:50] = 0  # a hole: its border is a depth edge
    depths[1, 0, 5, 7] = float("nan")
    views = Views(images, cams, depths)
    fast = RGBDReconstructor(**overrides)(views)
    ref = RGBDReconstructor(fast=False, **overrides)(views)
    assert torch.equal(fast.pixel_ids, ref.pixel_ids)
    a, b = fast.gaussians, ref.gaussians
    torch.testing.assert_close(a.means, b.means, rtol=0, atol=1e-5)
    torch.testing.assert_close(a.sh, b.sh, rtol=0, atol=1e-5)
    torch.testing.assert_close(a.opacities, b.opacities)
    sa, sb = (torch.as_tensor(r.render_options["saturation"]).expand(len(a)) for r in (fast, ref))
    torch.testing.assert_close(sa, sb, rtol=0, atol=1e-4)  # softened discs (curved surfaces) alike
    ca, cb = covariance_3d(a.quats, a.scales), covariance_3d(b.quats, b.scales)
    err = (ca - cb).abs().amax((1, 2)) / cb.abs().amax((1, 2))
    # the compiled arithmetic (float32, accurate to ~1e-6) and the PyTorch rule's (float32,
    # ~1e-5) may decide a depth-edge threshold differently for a handful of pixels, which
    # shrinks one axis of their discs by edge_scale: at most 1 - edge_scale^2 of the largest
    # covariance entry; everywhere else the covariances agree to round-off.
    assert (err < 1e-3).float().mean() > 0.999
    assert err.max() <= 1 - overrides.get("edge_scale", RGBDConfig.edge_scale) ** 2 + 1e-3
    assert torch.isfinite(ca).all()


def _disc_inputs(V=2, H=17, W=23, rotate=True):
    """Random images, depths of a rough slanted plane ~1 m away, off-centre cameras with
    fx != fy (rotated and moved)."""
    g = torch.Generator().manual_seed(0)
    u, v = torch.arange(W) / W, torch.arange(H)[:, None] / H
    z = 1 + 0.2 * u + 0.1 * v + 0.003 * torch.rand(V, H, W, generator=g)
    images = torch.rand(V, 3, H, W, generator=g)
    K = torch.tensor([[30.0, 0, 0.45 * W], [0, 36.0, 0.55 * H], [0, 0, 1]]).repeat(V, 1, 1)
    c2w = torch.eye(4).repeat(V, 1, 1)
    if rotate:
        c2w[1, :3, :3] = torch.tensor([[0.0, -0.8, 0.6], [0.6, -0.48, -0.64], [0.8, 0.36, 0.48]])
        c2w[:, :3, 3] = torch.tensor([0.3, -0.2, 1.0])
    return z, images, K, c2w


@pytest.mark.parametrize("stride", [1, 2, 3])
def test_compiled_discs_match_the_float64_rule_on_hard_depth_maps(stride):
    """Depth maps full of edges (holes, NaN and negative lines, sparse pixels, patches 1e4
    times farther and nearer, one at 1e30 m whose squared steps overflow float32, the image
    border, odd sizes): every compiled disc agrees with the PyTorch rule evaluated in
    float64, although the compiled one computes in float32."""
    from gensplat_transforms.core.rotations import covariance_3d
    from gensplat_transforms.geometry.discs_fast import surface_discs
    from gensplat_transforms.geometry.rgbd import RGBDConfig, dense_discs, grid_pixel_ids

    z, images, K, c2w = _disc_inputs()
    z[0, 3:7, 4:9] = 0
    z[0, 10, :] = float("nan")
    z[0, :, 15] = -1.0
    z[1, ::3, ::2] = 0
    z[1, 5:9, 10:14] *= 1e4
    z[1, 12:, :6] *= 1e-4
    z[0, 12:15, 18:21] = 1e30
    cfg = RGBDConfig(stride=stride, soften_noise=False)  # the disc rule alone
    means, quats, scales, dc, ids = surface_discs(
        z, images, K, c2w, stride, cfg.sigma_px, cfg.thickness, cfg.max_stretch, cfg.edge_scale
    )
    clean = torch.where(z > 0, z, 0).double()
    M, Q, S, D, _, keep = dense_discs(clean, images.double(), K.double(), c2w.double(), cfg)
    keep = keep.reshape(-1)
    assert torch.equal(ids, grid_pixel_ids(*z.shape[-2:], stride, len(z)).reshape(-1)[keep])
    M, Q, S, D = (t.reshape(-1, t.shape[-1])[keep] for t in (M, Q, S, D))
    torch.testing.assert_close(means.double(), M, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(dc.double(), D, rtol=0, atol=1e-6)
    torch.testing.assert_close(quats.norm(dim=1), torch.ones(len(quats)), rtol=0, atol=1e-6)
    ca, cb = covariance_3d(quats.double(), scales.double()), covariance_3d(Q, S)
    assert ((ca - cb).abs().amax((1, 2)) / cb.abs().amax((1, 2))).max() < 1e-5


def test_compiled_discs_scale_with_the_depth_and_stay_finite():
    """Depths times 2^e (e from -100 to 100; camera at the origin): the same rotations, and
    centres and scales times 2^e, bit for bit. Depths near the ends of float32's range next
    to ordinary ones (denormal included) give finite discs."""
    from gensplat_transforms.geometry.discs_fast import surface_discs

    z, images, K, c2w = _disc_inputs(rotate=False)
    z[0, 4:6, 5:9] = 0
    args = (images, K, c2w, 1, 0.4, 0.1, 4.0, 0.25)
    means, quats, scales, _, ids = surface_discs(z, *args)
    for e in (-100, -40, 40, 100):
        m, q, s, _, i = surface_discs(z * 2.0**e, *args)
        assert torch.equal(i, ids) and torch.equal(q, quats)
        assert torch.equal(m, means * 2.0**e) and torch.equal(s, scales * 2.0**e)
    for value in (1e-45, 1e-38, 1e-20, 1e20, 1e38):
        extreme = z.clone()
        extreme[:, 3:6, 7:12] = value
        extreme[1, 10, 3] = value  # a single pixel
        out = surface_discs(extreme, *args)
        assert len(out[0]) == (extreme > 0).sum() and all(torch.isfinite(t).all() for t in out[:4])


def test_fill_depth_gives_small_holes_the_farthest_depth_around():
    """A pixel between a near box (1 m) and the table behind (2 m) takes the table's depth, 3 %
    behind it; a wider gap fills from both sides, a pixel a round; a hole wider than twice the
    steps keeps its centre empty; measured depth is kept; no holes or steps 0: the map
    itself; negative steps are refused."""
    from gensplat_transforms.geometry.depth_fill import BEHIND, fill_depth

    assert BEHIND == 1.03
    assert torch.equal(fill_depth(torch.tensor([[1.0, 0.0, 2.0]]), 1), torch.tensor([[1.0, 2.0 * BEHIND, 2.0]]))
    row = torch.tensor([[1.0, 1.0, 0.0, 0.0, 2.0, 2.0]])
    assert torch.equal(fill_depth(row, 2), torch.tensor([[1.0, 1.0, BEHIND, 2.0 * BEHIND, 2.0, 2.0]]))
    wide = torch.cat([torch.ones(2), torch.zeros(7), torch.ones(2)])[None].expand(3, 11).contiguous()
    filled = fill_depth(wide, 3)
    assert filled[:, 2:5].eq(BEHIND).all() and filled[:, 6:9].eq(BEHIND).all() and not filled[:, 5].any()
    assert torch.equal(filled[:, :2], wide[:, :2])
    assert fill_depth(wide, 0) is wide and fill_depth(torch.ones(4, 4), 5).eq(1).all()
    # holes no depth can reach end the rounds at once, whatever the steps (a frame without depth)
    empty = torch.zeros(2, 64, 64)
    assert torch.equal(fill_depth(empty, 10**8), empty)
    island = torch.zeros(64, 64)
    island[0, 0] = 1.0
    assert fill_depth(island, 10**8).gt(0).all()  # one measured pixel fills a whole map, then the rounds end
    with pytest.raises(ValueError, match="steps must be >= 0"):
        fill_depth(wide, -1)


def test_filled_sensor_holes_get_discs_and_the_source_view_back(scene_views):
    """Depth with sensor-like holes (random pixels and a 6-pixel band): with fill_depth_px the
    holes get discs coloured by the image, so the source view comes back closer to the
    image; the default keeps the identity it always had, filling changes it."""
    _, cams, images, depths = scene_views
    holed = depths.clone()
    holed[torch.rand(holed.shape, generator=torch.Generator().manual_seed(0)) < 0.05] = 0
    holed[..., 20:26, :] = 0
    views = Views(images[:1], cams[:1], holed[:1])
    plain, filled = RGBDReconstructor().reconstruct(views), RGBDReconstructor(fill_depth_px=4).reconstruct(views)
    assert len(filled.gaussians) == SIZE * SIZE > len(plain.gaussians)
    back = [render(r.gaussians, cams[0], backend="fast").rgb[0] for r in (plain, filled)]
    assert psnr(back[1], images[0]) > psnr(back[0], images[0]) + 3
    assert RGBDReconstructor().identity() == "rgbd-b4a28c8cc49722ec"  # caches built before stay valid
    assert RGBDReconstructor(fill_depth_px=4).identity() != RGBDReconstructor().identity()
    with pytest.raises(ValueError, match="fill_depth_px"):
        RGBDReconstructor(fill_depth_px=-1)
    near_limit = RGBDReconstructor(fill_depth_px=1, max_depth=2.0)  # filled 3 % behind 1.99 m: beyond it
    assert torch.equal(near_limit.disc_depth(torch.tensor([[1.0, 0.0, 1.99]])), torch.tensor([[1.0, 0.0, 1.99]]))


def two_views(size: int = SIZE) -> Views:
    cams = default_cameras(size, size)[:2]
    images, depths = TabletopScene(0).render(cams)
    return Views(images, cams, depths)


def test_render_settings_leave_the_identity_and_travel_with_the_reconstruction():
    """dilation, saturation, view_preference, soften_noise and cover shape only what is drawn:
    caches stay valid."""
    views = two_views()
    sharp = RGBDReconstructor(dilation=0.1, saturation=2.0, view_preference=0.05, soften_noise=False, cover=0.6)
    assert sharp.identity() == RGBDReconstructor().identity() == "rgbd-b4a28c8cc49722ec"
    rec = sharp(views)
    assert rec.render_options == {"dilation": 0.1, "saturation": 2.0, "cover": 0.6} and rec.view_preference == 0.05
    default = RGBDReconstructor()(views)
    assert default.render_options["dilation"] == 0.04 and default.view_preference == 0.03
    per_disc = default.render_options["saturation"]  # the curved objects' discs are softened
    assert per_disc.shape == (len(default.gaussians),) and per_disc.min() >= 1 and per_disc.max() == 2.0
    for name, value in (("dilation", 0.0), ("dilation", float("nan")), ("saturation", 0.5),
                        ("saturation", float("inf")), ("view_preference", -0.1), ("view_preference", 2.0),
                        ("soften_noise", "false"), ("soften_noise", 1)):  # fmt: skip
        with pytest.raises(ValueError, match=f"RGBDConfig.{name}"):
            RGBDReconstructor(**{name: value})


def test_each_camera_draws_its_own_discs_in_front_where_both_saw_the_surface():
    """At a source camera's pose its discs stay put and the other camera's move back along
    the rays (image positions kept); preferring views lifts the source pose's PSNR."""
    views = two_views(size=48)
    rec = RGBDReconstructor()(views)
    left = rec.cameras[:1]
    moved = rec.seen_from(left)
    own = rec.pixel_ids < 48 * 48
    torch.testing.assert_close(moved.means[own], rec.gaussians.means[own], atol=1e-6, rtol=0)  # round-off only
    other = ~own
    before = rec.gaussians.means[other] - left.centers[0].float()
    after = moved.means[other] - left.centers[0].float()
    along = torch.nn.functional.cosine_similarity(before, after, dim=-1)
    assert along.min() > 1 - 1e-6  # along the ray
    ratio = after.norm(dim=-1) / before.norm(dim=-1)
    assert ratio.min() >= 1.0 and ratio.max() <= 1.03 + 1e-6 and ratio.max() > 1.025  # up to 3 % farther
    no_preference = replace(rec, view_preference=0.0)
    assert no_preference.seen_from(left) is rec.gaussians
    scores = [psnr(render(r.seen_from(left), left, **r.render_options).rgb[0], views.images[0])
              for r in (no_preference, rec)]  # fmt: skip
    assert scores[1] > scores[0] + 0.5


def test_preferred_means_stays_finite_for_degenerate_rays():
    means = torch.tensor([[0.0, 0, 0], [1e6, -1e6, 1e6], [0.0, 0, 1.0], [0.0, 0, 2.0]])
    origins = torch.tensor([[0.0, 0, 0], [0.0, 0, 0], [0.0, 0, 1.0], [1.0, 0, 0]])  # a mean at its camera
    out = preferred_means(means, source_rays(means, origins), torch.zeros(3), 0.02)  # and at the viewing camera's centre
    assert torch.isfinite(out).all() and torch.equal(out[0], means[0])
    assert out[3, 2] == pytest.approx(2.0 * 1.02)  # 1 - cos(26.6 deg) > 0.04: the full 2 %


def test_compiled_source_rays_match_the_tensor_rule():
    """Float32 CPU means (the workers') take a compiled pass: the same rays as tensor
    operations in float64, to float32 rounding; a mean at its camera's centre gets a zero ray."""
    g = torch.Generator().manual_seed(3)
    means, centers = torch.randn(4000, 3, generator=g), torch.randn(3, 3, generator=g)
    ids = torch.randint(0, 3 * 60, (4000,), generator=g)
    means[7] = centers[int(ids[7]) // 60]
    got = pixel_rays(means, ids, centers, 60)
    want = pixel_rays(means.double(), ids, centers.double(), 60)  # float64: tensor operations
    assert got.dtype == torch.float32 and torch.equal(got[7], torch.zeros(3))
    torch.testing.assert_close(got.double(), want, rtol=0, atol=1e-6)
    torch.testing.assert_close(want, source_rays(means.double(), centers.double()[ids // 60]), rtol=0, atol=0)


def test_pixel_ids_beyond_the_cameras_pixels_are_refused():
    """A Reconstruction's pixel ids name a pixel of its cameras; the compiled rays (no bounds
    checks of their own in compiled code) refuse any other instead of reading past the centres,
    and the tensor rule (float64, GPU) any other instead of indexing from the end."""
    rec = RGBDReconstructor()(two_views(size=12))
    n = len(rec.gaussians)
    for bad in (-1, 2 * 12 * 12):
        ids = rec.pixel_ids.clone()
        ids[n // 2] = bad
        with pytest.raises(ValueError, match=r"pixel_ids: must lie in 0..287 \(the 2 cameras' pixels\)"):
            Reconstruction(rec.gaussians, rec.cameras, ids)
        for dtype in (torch.float32, torch.float64):  # the compiled pass, the tensor rule
            with pytest.raises(IndexError, match="a pixel id beyond the cameras' pixels"):
                pixel_rays(rec.gaussians.means.to(dtype), ids, rec.cameras.centers.to(dtype), 12 * 12)
    means, centers = rec.gaussians.means, rec.cameras.centers.float()
    with pytest.raises(ValueError, match=r"pixel_rays: need means \(N, 3\), pixel_ids \(N,\)"):
        pixel_rays(means, rec.pixel_ids[:-1], centers, 12 * 12)
    with pytest.raises(ValueError, match=r"preferred_means: means .* and rays .* differ in shape"):
        preferred_means(means, rec.rays[:-1], centers[0], 0.02)


def test_compiled_preference_matches_the_tensor_rule():
    """The workers' compiled push (float32 CPU Gaussians) against the tensor rule (which
    ``preferred_means`` runs in float64): random means and cameras, a mean at the viewing
    camera's centre, a zero source ray."""
    from gensplat_transforms.core.views import _preferred_means_cpu

    g = torch.Generator().manual_seed(5)
    means = torch.randn(5000, 3, generator=g) * 2
    origins = torch.randn(5000, 3, generator=g)
    means[0] = torch.tensor([0.5, -0.5, 1.0])  # at the viewing camera's centre
    origins[1] = means[1]  # a mean at its own camera: zero ray
    rays, center = source_rays(means, origins), torch.tensor([0.5, -0.5, 1.0])
    expected = preferred_means(means.double(), rays.double(), center.double(), 0.03).float()
    got = _preferred_means_cpu(means, rays, center, 0.03)
    assert torch.equal(preferred_means(means, rays, center, 0.03), got)  # float32 CPU: the compiled pass
    assert torch.isfinite(got).all() and torch.equal(got[0], means[0])
    torch.testing.assert_close(got, expected, rtol=1e-6, atol=1e-6)
    views = two_views(size=24)
    rec = RGBDReconstructor()(views)
    camera = rec.cameras[1:]
    torch.testing.assert_close(rec.seen_from(camera).means,  # the worker's path: compiled
                               preferred_means(rec.gaussians.means.double(), rec.rays.double(),
                                               camera.centers[0].double(), rec.view_preference).float(),
                               rtol=1e-6, atol=1e-6)  # fmt: skip


@pytest.mark.parametrize("fast", [True, False])
def test_only_the_nearer_side_of_a_depth_jump_shrinks_and_a_hole_is_no_edge(fast):
    """A foreground disc beside a depth jump shrinks across it (it would overhang the
    background); the background disc beside it keeps its size (it lies behind and fills the
    view that opens there), and so do discs beside pixels without depth."""
    H = W = 8
    z = torch.ones(1, 1, H, W)
    z[..., 4:] = 2.0  # columns 4.. twice as far: a jump between columns 3 and 4
    z[..., 6, 1] = 0.0  # a pixel without depth in the near half
    K = torch.tensor([[[10.0, 0, 4], [0, 10.0, 4], [0, 0, 1]]], dtype=torch.float64)
    views = Views(torch.full((1, 3, H, W), 0.5), Cameras(K, torch.eye(4, dtype=torch.float64)[None], W, H), z)
    rec = RGBDReconstructor(fast=fast, soften_noise=False).reconstruct(views)
    footprint = rec.gaussians.scales[:, :2].amin(1) / rec.gaussians.means[:, 2]  # in-plane size / depth
    size = dict(zip(rec.pixel_ids.tolist(), footprint.tolist()))
    plain = size[2 * W + 1]  # an interior pixel of the near half
    torch.testing.assert_close(torch.tensor(size[2 * W + 3]), torch.tensor(plain * RGBDConfig.edge_scale))  # near side
    torch.testing.assert_close(torch.tensor(size[2 * W + 4]), torch.tensor(plain))  # far side: as inside
    for beside_hole in (5 * W + 1, 6 * W + 0, 6 * W + 2, 7 * W + 1):
        torch.testing.assert_close(torch.tensor(size[beside_hole]), torch.tensor(plain))
    assert 6 * W + 1 not in size
