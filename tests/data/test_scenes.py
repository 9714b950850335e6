"""The procedural tabletop scene: determinism, exact geometry, view-independent colour,
default cameras and resolution consistency."""

import math

import pytest
import torch

from gensplat_transforms import Cameras, look_at, pivot_point
from gensplat_transforms.data.scenes import (
    AMBIENT,
    BACKGROUND_RGB,
    LABEL_FIRST_OBJECT,
    LABEL_NONE,
    LABEL_ROOM,
    LABEL_TABLE,
    LIGHT_DIR,
    ROOM_CENTER,
    ROOM_HALF_SIZE,
    TABLE_CENTER,
    TABLE_HALF_SIZE,
    WORKSPACE_SIZE,
    TabletopScene,
    default_cameras,
)


@pytest.fixture(scope="module")
def scene():
    return TabletopScene(seed=0)


@pytest.fixture(scope="module")
def default_render(scene):
    cams = default_cameras()
    rgb, depth = scene.render(cams)
    return cams, rgb, depth, scene.labels(cams)


def box_sdf(p, center, half, yaw=0.0):
    """Signed distance (N,) from points p (N, 3) to a z-rotated box."""
    c, s = math.cos(yaw), math.sin(yaw)
    rot = torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=p.dtype)
    q = ((p - p.new_tensor(center)) @ rot).abs() - p.new_tensor(half)
    return q.clamp(min=0).norm(dim=-1) + q.amax(-1).clamp(max=0)


def object_sdf(obj, p):
    if obj.kind == "box":
        return box_sdf(p, obj.center, obj.half_size, obj.yaw)
    q = p - p.new_tensor(obj.center)
    r, h = obj.half_size[0], obj.half_size[2]
    if obj.kind == "sphere":
        return q.norm(dim=-1) - r
    e = torch.stack([q[:, :2].norm(dim=-1) - r, q[:, 2].abs() - h], -1)
    return e.clamp(min=0).norm(dim=-1) + e.amax(-1).clamp(max=0)


def centered_camera(eye, target, size=33, f=40.0):
    """Odd-sized camera whose central pixel centre lies exactly on the ray eye -> target."""
    return Cameras.from_intrinsics(f, f, size / 2, size / 2, look_at(eye, target), size, size)


def test_seed_determines_the_scene():
    cams = default_cameras(48, 40)
    a, b, c = TabletopScene(3), TabletopScene(3), TabletopScene(4)
    assert a.objects == b.objects and a.objects != c.objects
    assert 5 <= len(a.objects) <= 8
    rgb_a, depth_a = a.render(cams)
    rgb_b, depth_b = b.render(cams)
    rgb_c, _ = c.render(cams)
    assert torch.equal(rgb_a, rgb_b) and torch.equal(depth_a, depth_b)
    assert (rgb_a - rgb_c).abs().amax() > 0.1


@pytest.mark.parametrize("seed", range(6))
def test_objects_rest_inside_the_workspace_without_overlap(seed):
    objects = TabletopScene(seed).objects
    assert {"box", "sphere", "cylinder"} <= {o.kind for o in objects}
    for i, o in enumerate(objects):
        x, y, z = o.center
        reach = math.hypot(o.half_size[0], o.half_size[1]) if o.kind == "box" else o.half_size[0]
        assert abs(x) + reach <= WORKSPACE_SIZE[0] / 2 + 1e-9
        assert abs(y) + reach <= WORKSPACE_SIZE[1] / 2 + 1e-9
        assert z == pytest.approx(o.half_size[2])  # resting on the table top z = 0
        for p in objects[i + 1:]:
            p_reach = math.hypot(p.half_size[0], p.half_size[1]) if p.kind == "box" else p.half_size[0]
            assert math.hypot(x - p.center[0], y - p.center[1]) > reach + p_reach


def test_shapes_dtypes_and_range(scene):
    cams = default_cameras(64, 48)
    rgb, depth = scene.render(cams)
    labels = scene.labels(cams)
    assert rgb.shape == (3, 3, 48, 64) and rgb.dtype == torch.float32
    assert depth.shape == (3, 1, 48, 64) and depth.dtype == torch.float32
    assert labels.shape == (3, 1, 48, 64) and labels.dtype == torch.int64
    assert rgb.min() >= 0 and rgb.max() <= 1 and rgb.std() > 0.05


def test_every_default_pixel_hits_and_everything_is_seen(scene, default_render):
    cams, _, depth, labels = default_render
    assert len(cams) == 3 and (cams.width, cams.height) == (224, 224)
    assert torch.isfinite(depth).all() and (depth > 0).all()
    assert (labels != LABEL_NONE).all()
    for view in labels:
        assert (view == LABEL_TABLE).float().mean() > 0.3
    seen = set(labels.unique().tolist())
    assert set(range(LABEL_FIRST_OBJECT, LABEL_FIRST_OBJECT + len(scene.objects))) <= seen


def test_unprojected_depth_lies_on_the_labelled_surface(scene, default_render):
    cams, _, depth, labels = default_render
    uv = cams.pixel_centers()[None].expand(len(cams), -1, -1)
    points = cams.unproject(uv, depth.flatten(1).double()).reshape(-1, 3)
    labels = labels.flatten()
    table = points[labels == LABEL_TABLE]
    assert box_sdf(table, TABLE_CENTER, TABLE_HALF_SIZE).abs().max() < 1e-4
    on_top = (table[:, :2].abs() < table.new_tensor(TABLE_HALF_SIZE[:2]) - 1e-3).all(-1)  # not a side face
    assert on_top.float().mean() > 0.9 and table[on_top, 2].abs().max() < 1e-4
    room = points[labels == LABEL_ROOM]
    assert box_sdf(room, ROOM_CENTER, ROOM_HALF_SIZE).abs().max() < 1e-4
    for i, obj in enumerate(scene.objects):
        hits = points[labels == LABEL_FIRST_OBJECT + i]
        assert object_sdf(obj, hits).abs().max() < 1e-4, obj.kind


def test_object_tops_seen_from_above_have_exact_depth_and_lambertian_colour(scene):
    shade = AMBIENT + (1 - AMBIENT) * LIGHT_DIR[2]  # the top's normal is +Z
    for i, obj in enumerate(scene.objects):
        top = torch.tensor(obj.top, dtype=torch.float64)
        colours = []
        for offset in ((0.05, 0.0, 0.6), (-0.03, 0.08, 0.45)):
            eye = top + torch.tensor(offset, dtype=torch.float64)
            cam = centered_camera(eye, top)
            rgb, depth = scene.render(cam)
            assert scene.labels(cam)[0, 0, 16, 16] == LABEL_FIRST_OBJECT + i
            assert depth[0, 0, 16, 16].item() == pytest.approx((top - eye).norm().item(), abs=1e-3)
            colours.append(rgb[0, :, 16, 16])
        torch.testing.assert_close(colours[0], colours[1], atol=1e-6, rtol=0)  # view-independent
        albedo = colours[0].double() / shade
        lo = torch.minimum(torch.tensor(obj.color), torch.tensor(obj.stripe_color)).double()
        hi = torch.maximum(torch.tensor(obj.color), torch.tensor(obj.stripe_color)).double()
        assert ((albedo >= lo - 1e-4) & (albedo <= hi + 1e-4)).all(), (obj.kind, albedo, lo, hi)


def test_object_centres_project_onto_the_object(scene, default_render):
    cams, _, _, labels = default_render
    centers = torch.tensor([o.center for o in scene.objects], dtype=torch.float64)
    uv, z = cams.project(centers)
    assert (z > 0).all()
    col, row = uv[..., 0].floor().long(), uv[..., 1].floor().long()
    inside = (col >= 0) & (col < cams.width) & (row >= 0) & (row < cams.height)
    assert inside.all()
    seen = labels[torch.arange(3)[:, None], 0, row, col]  # (views, objects)
    expected = LABEL_FIRST_OBJECT + torch.arange(len(scene.objects))
    assert (seen == expected).any(0).all()  # each object is unoccluded in at least one view


def test_default_cameras_layout_and_pivot():
    cams = default_cameras()
    centers = cams.centers
    assert centers[0, 1] > 0 > centers[1, 1]  # order: left (+y), right (-y), front
    for c in centers[:2]:
        assert 0.7 <= c.norm() <= 1.0 and 0.4 <= c[2] <= 0.6
    pivot = pivot_point(cams.c2w[0], cams.c2w[1])
    assert 0.0 < pivot[2] < 0.15 and pivot[:2].norm() < 0.1
    uv, z = cams.project(pivot[None])
    assert (z > 0).all()
    assert ((uv > 0.2 * 224) & (uv < 0.8 * 224)).all()


def test_fov_sets_vertical_focal_length():
    cams = default_cameras(width=320, height=240, fov_deg=50.0)
    _, fovy = cams.fov_deg()
    torch.testing.assert_close(fovy, torch.full((3,), 50.0, dtype=torch.float64))
    assert cams.K[0, 0, 2] == 160 and cams.K[0, 1, 2] == 120


def test_resolutions_agree_on_shared_pixel_centres(scene):
    small = default_cameras(32, 24)
    large = small.resize(96, 72)  # pixel j of the small image has the centre of pixel 3j+1
    rgb_s, depth_s = scene.render(small)
    rgb_l, depth_l = scene.render(large)
    torch.testing.assert_close(rgb_l[..., 1::3, 1::3], rgb_s, atol=1e-5, rtol=0)
    torch.testing.assert_close(depth_l[..., 1::3, 1::3], depth_s, atol=1e-5, rtol=1e-6)


def test_rays_that_miss_everything_get_depth_zero_and_background(scene):
    cam = centered_camera((5.0, 0.0, 0.0), (10.0, 0.0, 1.0), size=9)  # outside the room, looking away
    rgb, depth = scene.render(cam)
    assert (depth == 0).all() and (scene.labels(cam) == LABEL_NONE).all()
    torch.testing.assert_close(rgb, torch.tensor(BACKGROUND_RGB).view(1, 3, 1, 1).expand_as(rgb))
