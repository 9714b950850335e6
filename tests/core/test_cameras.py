"""Tests for gensplat_transforms.core.cameras (OpenCV pinhole cameras, camera-to-world poses)."""

from __future__ import annotations

import math

import pytest
import torch
from PIL import Image

from gensplat_transforms.core import cameras as cameras_module
from gensplat_transforms.core.cameras import (
    Cameras,
    focal_from_fov,
    look_at,
    opencv_to_opengl,
    opengl_to_opencv,
    rigid_inverse,
)

W, H = 64, 48
DTYPE = torch.float64


@pytest.fixture
def cams() -> Cameras:
    """Three cameras with different intrinsics looking at points near the origin."""
    c2w = torch.stack(
        [
            look_at((1.5, -0.4, 0.8), (0.0, 0.0, 0.1)),
            look_at((-0.3, 1.2, 1.0), (0.1, -0.1, 0.0)),
            look_at((0.2, 0.3, -2.0), (0.0, 0.0, 0.0)),
        ]
    )
    return Cameras.from_intrinsics(
        torch.tensor([50.0, 61.0, 45.5], dtype=DTYPE),
        torch.tensor([52.0, 60.0, 47.0], dtype=DTYPE),
        torch.tensor([32.0, 30.5, 33.0], dtype=DTYPE),
        torch.tensor([24.0, 22.0, 25.5], dtype=DTYPE),
        c2w,
        W,
        H,
    )


def random_pixels(n: int, width: int, height: int, seed: int = 0, margin: float = 0.05) -> torch.Tensor:
    """(n, 2) continuous pixel coordinates at least ``margin`` px from every pixel border."""
    g = torch.Generator().manual_seed(seed)
    ij = torch.stack(
        [torch.randint(0, width, (n,), generator=g), torch.randint(0, height, (n,), generator=g)], -1
    )
    frac = margin + (1 - 2 * margin) * torch.rand(n, 2, generator=g, dtype=DTYPE)
    return ij.to(DTYPE) + frac


# ---------------------------------------------------------------------------- constructors
def test_from_intrinsics_scalars_and_per_camera_values(cams):
    one = Cameras.from_intrinsics(100.0, 90.0, 32.0, 24.0, torch.eye(4, dtype=DTYPE), W, H)
    expected = torch.tensor([[100.0, 0, 32.0], [0, 90.0, 24.0], [0, 0, 1.0]], dtype=DTYPE)
    assert len(one) == 1 and one.K.shape == (1, 3, 3) and one.c2w.shape == (1, 4, 4)
    torch.testing.assert_close(one.K[0], expected)
    assert (one.width, one.height) == (W, H)
    # per-camera tensors land on the right camera
    torch.testing.assert_close(cams.K[:, 0, 0], torch.tensor([50.0, 61.0, 45.5], dtype=DTYPE))
    torch.testing.assert_close(cams.K[:, 1, 2], torch.tensor([24.0, 22.0, 25.5], dtype=DTYPE))
    assert (cams.K[:, 2] == torch.tensor([0.0, 0.0, 1.0], dtype=DTYPE)).all()


def test_from_opengl_matches_manual_flip_on_droid(droid):
    cams = Cameras.from_opengl(droid.K, droid.c2w_gl, droid.width, droid.height)
    torch.testing.assert_close(cams.c2w, droid.cameras.c2w, rtol=0, atol=1e-15)
    assert Cameras.from_nerfstudio == Cameras.from_opengl
    # OpenGL looks along -z with y up: OpenCV forward = -z_gl, OpenCV down = -y_gl, same centre
    torch.testing.assert_close(cams.forward, -droid.c2w_gl[:, :3, 2])
    torch.testing.assert_close(cams.c2w[:, :3, 1], -droid.c2w_gl[:, :3, 1])
    torch.testing.assert_close(cams.centers, droid.c2w_gl[:, :3, 3])
    torch.testing.assert_close(opencv_to_opengl(cams.c2w), droid.c2w_gl)  # the flip is an involution
    assert (droid.width, droid.height) == (1280, 720)


def test_droid_images_match_the_intrinsics(droid, droid_dir):
    for name in droid.names:
        with Image.open(droid_dir / name) as im:
            assert im.size == (droid.width, droid.height), name


def test_droid_poses_are_rigid(droid):
    R = droid.cameras.c2w[:, :3, :3]
    torch.testing.assert_close(
        R @ R.transpose(1, 2), torch.eye(3, dtype=DTYPE).expand(2, 3, 3), atol=1e-6, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(2, dtype=DTYPE), atol=1e-6, rtol=0)


def _mujoco_xmat(forward_gl_axes: str) -> torch.Tensor:
    """MuJoCo camera frames (columns x, y, z in world; the camera looks along -z, y up)."""
    if forward_gl_axes == "down":  # identity: looks along world -z, image up = world +y
        return torch.eye(3, dtype=DTYPE)
    # looks along world +x with world +z up: z_cam = -x, y_cam = +z, x_cam = y_cam x z_cam = -y
    return torch.tensor([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], dtype=DTYPE)


@pytest.mark.parametrize("pose", ["down", "along_x"])
def test_from_mujoco(pose):
    fovy, width, height = 45.0, 80, 60
    pos = torch.tensor([0.3, -0.2, 1.0], dtype=DTYPE)
    xmat = _mujoco_xmat(pose)
    # MuJoCo's data.cam_xmat is the (9,) row-major flattening of the camera frame
    cam = Cameras.from_mujoco(pos[None], xmat.reshape(1, 9), fovy, width, height)
    f = (height / 2) / math.tan(math.radians(fovy) / 2)
    torch.testing.assert_close(cam.K[0], torch.tensor([[f, 0, 40.0], [0, f, 30.0], [0, 0, 1]], dtype=DTYPE))
    fwd, up = (-xmat[:, 2], xmat[:, 1])  # world directions of the view and of image-up
    torch.testing.assert_close(cam.forward[0], fwd)
    # a point straight ahead hits the principal point; one at the top of the fovy cone hits v = 0
    top = pos + fwd + math.tan(math.radians(fovy) / 2) * up
    uv, z = cam.project(torch.stack([pos + 2 * fwd, top]))
    torch.testing.assert_close(uv[0], torch.tensor([[40.0, 30.0], [40.0, 0.0]], dtype=DTYPE))
    torch.testing.assert_close(z[0], torch.tensor([2.0, 1.0], dtype=DTYPE))
    same = Cameras.from_mujoco(pos[None], xmat[None], fovy, width, height)  # (B, 3, 3) accepted too
    torch.testing.assert_close(same.c2w, cam.c2w)


# ---------------------------------------------------------------------------- geometry
def test_project_known_point_and_pixel_centre_convention():
    K = torch.tensor([[100.0, 0, 2.0], [0, 80.0, 1.5], [0, 0, 1]], dtype=DTYPE)
    cam = Cameras(K, torch.eye(4, dtype=DTYPE), 4, 3)  # principal point at the image centre (W/2, H/2)
    uv, z = cam.project(torch.tensor([[0.0, 0.0, 2.0], [0.1, -0.05, 2.0]], dtype=DTYPE))
    torch.testing.assert_close(
        uv[0], torch.tensor([[2.0, 1.5], [2.0 + 100 * 0.05, 1.5 - 80 * 0.025]], dtype=DTYPE)
    )
    torch.testing.assert_close(z[0], torch.tensor([2.0, 2.0], dtype=DTYPE))
    centers = cam.pixel_centers()
    assert centers.shape == (12, 2)
    # row-major: entry i*W + j is pixel (row i, col j) with centre (j + 0.5, i + 0.5)
    for i, j in [(0, 0), (0, 3), (2, 1), (2, 3)]:
        torch.testing.assert_close(centers[i * 4 + j], torch.tensor([j + 0.5, i + 0.5], dtype=DTYPE))


def test_points_behind_camera_have_negative_depth(cams):
    pts = cams.centers - cams.forward  # 1 m behind each camera
    _, z = cams.project(pts[:, None])
    torch.testing.assert_close(z, -torch.ones(3, 1, dtype=DTYPE))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_unproject_project_round_trip(cams, dtype):
    uv = random_pixels(200, W, H).to(dtype).expand(len(cams), -1, -1)
    depth = torch.linspace(0.1, 5.0, 200, dtype=dtype).expand(len(cams), -1)
    world = cams.unproject(uv, depth)
    assert world.shape == (3, 200, 3) and world.dtype == dtype
    uv2, depth2 = cams.project(world)
    tol = {"rtol": 1e-4, "atol": 1e-3} if dtype == torch.float32 else {"rtol": 1e-10, "atol": 1e-9}
    torch.testing.assert_close(uv2, uv, **tol)
    torch.testing.assert_close(depth2, depth, **tol)
    # depth is camera z (not ray length): distance along the optical axis
    dz = ((world - cams.centers[:, None].to(dtype)) * cams.forward[:, None].to(dtype)).sum(-1)
    torch.testing.assert_close(dz, depth, **tol)


def test_project_broadcasts_shared_points(cams):
    pts = torch.randn(10, 3, dtype=DTYPE, generator=torch.Generator().manual_seed(0))
    uv, z = cams.project(pts)
    uv_b, z_b = cams.project(pts.expand(3, -1, -1))
    assert uv.shape == (3, 10, 2) and z.shape == (3, 10)
    torch.testing.assert_close(uv, uv_b)
    torch.testing.assert_close(z, z_b)


def test_w2c_is_the_rigid_inverse(cams):
    w2c = cams.w2c()
    torch.testing.assert_close(w2c @ cams.c2w, torch.eye(4, dtype=DTYPE).expand(3, 4, 4), atol=1e-12, rtol=0)
    torch.testing.assert_close(w2c, torch.linalg.inv(cams.c2w))
    torch.testing.assert_close(rigid_inverse(w2c), cams.c2w)
    # the camera centre maps to the camera-frame origin
    torch.testing.assert_close(
        (w2c[:, :3, :3] @ cams.centers[..., None])[..., 0] + w2c[:, :3, 3],
        torch.zeros(3, 3, dtype=DTYPE),
        atol=1e-12,
        rtol=0,
    )


def test_w2c_is_differentiable(cams):
    c2w = cams.c2w.clone().requires_grad_(True)
    Cameras(cams.K, c2w, W, H).project(torch.ones(1, 3, dtype=DTYPE))[0].sum().backward()
    assert c2w.grad is not None and torch.isfinite(c2w.grad).all() and c2w.grad.abs().sum() > 0


# ---------------------------------------------------------------------------- resize / crop
def _world_points_inside(cams: Cameras, n: int = 300) -> torch.Tensor:
    uv = random_pixels(n, cams.width, cams.height, seed=1)[None]
    depth = torch.linspace(0.5, 3.0, n, dtype=DTYPE)[None]
    return cams[0].unproject(uv, depth)[0]


def _label_under(image: torch.Tensor, uv: torch.Tensor) -> torch.Tensor:
    """Value of the pixel that contains continuous coordinate uv (pixel centre at +0.5)."""
    return image[uv[:, 1].floor().long(), uv[:, 0].floor().long()]


@pytest.mark.parametrize("factor", [2, 3])
def test_resize_keeps_world_points_on_the_same_image_content(cams, factor):
    cam = cams[0]
    image = torch.randperm(W * H).reshape(H, W)  # every pixel has a unique label
    big = image.repeat_interleave(factor, 0).repeat_interleave(factor, 1)  # exact integer upsampling
    pts = _world_points_inside(cam)
    uv = cam.project(pts)[0][0]
    up = cam.resize(W * factor, H * factor)
    uv_up = up.project(pts)[0][0]
    assert (up.width, up.height) == (W * factor, H * factor)
    assert torch.equal(_label_under(big, uv_up), _label_under(image, uv))
    torch.testing.assert_close(uv_up, uv * factor)
    # and back down (block averaging of ``big`` is ``image`` again): the original intrinsics
    torch.testing.assert_close(up.resize(W, H).K, cam.K)


def test_resize_maps_image_corners_to_image_corners(droid):
    cams = droid.cameras
    small = cams.resize(224, 224)
    K, K2 = cams.K, small.K
    torch.testing.assert_close(K2[:, 0, 0], K[:, 0, 0] * 224 / 1280)
    torch.testing.assert_close(K2[:, 1, 1], K[:, 1, 1] * 224 / 720)
    for corner, scaled in [
        ((0.0, 0.0), (0.0, 0.0)),
        ((1280.0, 720.0), (224.0, 224.0)),
        ((640.0, 360.0), (112.0, 112.0)),
    ]:
        uv = torch.tensor(corner, dtype=DTYPE).expand(2, 1, 2)
        world = cams.unproject(uv, torch.ones(2, 1, dtype=DTYPE))
        torch.testing.assert_close(small.project(world)[0], torch.tensor(scaled, dtype=DTYPE).expand(2, 1, 2))
    torch.testing.assert_close(small.c2w, cams.c2w)


@pytest.mark.parametrize("window", [(0, 0, W, H), (5, 7, 30, 20), (W - 10, H - 4, 10, 4)])
def test_crop_keeps_world_points_on_the_same_image_content(cams, window):
    left, top, w, h = window
    cam = cams[0]
    image = torch.randperm(W * H).reshape(H, W)
    sub = image[top : top + h, left : left + w]
    pts = _world_points_inside(cam, 2000)
    uv = cam.project(pts)[0][0]
    cropped = cam.crop(left, top, w, h)
    uv_c = cropped.project(pts)[0][0]
    torch.testing.assert_close(uv_c, uv - torch.tensor([left, top], dtype=DTYPE))
    inside = (uv_c[:, 0] >= 0) & (uv_c[:, 0] < w) & (uv_c[:, 1] >= 0) & (uv_c[:, 1] < h)
    assert inside.sum() >= 10  # the window really sees some of the points
    assert torch.equal(_label_under(sub, uv_c[inside]), _label_under(image, uv[inside]))
    assert (cropped.width, cropped.height) == (w, h)


@pytest.mark.parametrize(
    "window", [(-1, 0, 10, 10), (0, -1, 10, 10), (60, 0, 10, 10), (0, 40, 10, 10), (0, 0, 0, 10)]
)
def test_crop_outside_the_image_raises(cams, window):
    with pytest.raises(ValueError):
        cams.crop(*window)


def test_crop_then_resize_composes(cams):
    pts = _world_points_inside(cams[0])
    a = cams.crop(8, 4, 32, 24).resize(64, 48)  # 2x zoom into the window
    uv = cams.project(pts)[0]
    torch.testing.assert_close(a.project(pts)[0], (uv - torch.tensor([8.0, 4.0], dtype=DTYPE)) * 2)


# ---------------------------------------------------------------------------- look_at, fov
def test_look_at_convention():
    eye, target = torch.tensor([1.0, -2.0, 0.5], dtype=DTYPE), torch.tensor([0.2, 0.3, 0.1], dtype=DTYPE)
    c2w = look_at(eye, target)
    R = c2w[:3, :3]
    torch.testing.assert_close(R.T @ R, torch.eye(3, dtype=DTYPE))
    assert torch.linalg.det(R) == pytest.approx(1.0)
    torch.testing.assert_close(c2w[3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=DTYPE))
    cam = Cameras.from_intrinsics(50.0, 50.0, 32.0, 24.0, c2w, W, H)
    up = torch.tensor([0.0, 0.0, 0.1], dtype=DTYPE)
    uv, z = cam.project(torch.stack([target, target + up]))
    # the target lands on the principal point, at its distance along the axis
    torch.testing.assert_close(uv[0, 0], torch.tensor([32.0, 24.0], dtype=DTYPE))
    assert z[0, 0] == pytest.approx(float((target - eye).norm()))
    assert uv[0, 1, 1] < uv[0, 0, 1]  # world up appears higher in the image (y points down)
    assert abs(uv[0, 1, 0] - 32.0) < 1e-9  # and stays on the vertical through the centre (no roll)


@pytest.mark.parametrize("target", [(1.0, 0.0, 5.0), (1.0, 0.0, -3.0), (1.0, 0.0, 0.0)])
def test_look_at_degenerate_raises(target):
    with pytest.raises(ValueError, match="look_at"):
        look_at((1.0, 0.0, 0.0), target)  # straight up, straight down, eye == target


def test_fov_and_focal_from_fov_agree():
    f = focal_from_fov(60.0, W)
    cam = Cameras.from_intrinsics(f, focal_from_fov(45.0, H), W / 2, H / 2, torch.eye(4, dtype=DTYPE), W, H)
    fovx, fovy = cam.fov_deg()
    assert fovx.item() == pytest.approx(60.0) and fovy.item() == pytest.approx(45.0)
    # the image's left edge is 30 degrees off axis
    edge = torch.tensor([[-math.tan(math.radians(30.0)), 0.0, 1.0]], dtype=DTYPE)
    assert cam.project(edge)[0][0, 0, 0].item() == pytest.approx(0.0, abs=1e-9)


# ---------------------------------------------------------------------------- batching
def test_getitem_keeps_the_batch_dimension(cams):
    for i in (0, 2, -1, -3):
        one = cams[i]
        assert len(one) == 1
        torch.testing.assert_close(one.c2w[0], cams.c2w[i])
        torch.testing.assert_close(one.K[0], cams.K[i])
    assert len(cams[1:]) == 2 and len(cams[torch.tensor([True, False, True])]) == 2
    for i in (3, -4):
        with pytest.raises(IndexError):
            cams[i]


def test_cat_and_with_c2w(cams):
    both = Cameras.cat([cams, cams[1]])
    assert len(both) == 4
    torch.testing.assert_close(both.c2w[3], cams.c2w[1])
    torch.testing.assert_close(both.K[:3], cams.K)
    with pytest.raises(ValueError, match="image size"):
        Cameras.cat([cams, cams.resize(2 * W, 2 * H)])
    moved = cams[0].with_c2w(cams.c2w)
    assert len(moved) == 3 and (moved.K == cams.K[0]).all()


def test_to_dtype(cams):
    c32 = cams.to(dtype=torch.float32)
    assert c32.dtype == torch.float32 and c32.K.dtype == torch.float32
    torch.testing.assert_close(c32.c2w.double(), cams.c2w, atol=1e-6, rtol=0)


# ---------------------------------------------------------------------------- validation
_GOOD_K, _GOOD_C2W = torch.eye(3, dtype=DTYPE), torch.eye(4, dtype=DTYPE)


def _nan(t: torch.Tensor, idx) -> torch.Tensor:
    t = t.clone()
    t[idx] = float("nan")
    return t


@pytest.mark.parametrize(
    ("K", "c2w", "width", "height", "match"),
    [
        (torch.eye(4, dtype=DTYPE), _GOOD_C2W, W, H, "K must be"),
        (_GOOD_K, torch.eye(3, dtype=DTYPE), W, H, "c2w"),
        (torch.eye(3, dtype=DTYPE).expand(2, 2, 3, 3), _GOOD_C2W.expand(2, 4, 4), W, H, "K must be"),
        (torch.ones(9, dtype=DTYPE), _GOOD_C2W, W, H, "K must be"),
        (_GOOD_K.expand(2, 3, 3), _GOOD_C2W.expand(3, 4, 4), W, H, "2 intrinsics but 3 poses"),
        (_GOOD_K, _GOOD_C2W, 0, H, "positive"),
        (_GOOD_K, _GOOD_C2W, W, -5, "positive"),
        (_nan(_GOOD_K, (0, 0)), _GOOD_C2W, W, H, "Cameras.K: contains NaN"),
        (_GOOD_K, _nan(_GOOD_C2W, (1, 3)), W, H, "Cameras.c2w: contains NaN"),
        (_GOOD_K, _GOOD_C2W * float("inf"), W, H, "Cameras.c2w: contains NaN or Inf"),
    ],
)
def test_bad_cameras_raise(K, c2w, width, height, match):
    with pytest.raises(ValueError, match=match):
        Cameras(K, c2w, width, height)


def _edit(t: torch.Tensor, idx, value) -> torch.Tensor:
    t = t.clone()
    t[idx] = value
    return t


_POSE = look_at((0.3, -0.2, -1.0), (0.0, 0.1, 0.5))
_MIRROR = _POSE @ torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=DTYPE))


@pytest.mark.parametrize(
    ("K", "c2w", "match"),
    [
        (_edit(_GOOD_K, (0, 0), 0.0), _GOOD_C2W, r"Cameras.K: focal lengths must be > 0 and at most 1e\+12 px, got fx, fy = \[0.0, 1.0\]"),
        (_edit(_GOOD_K, (1, 1), 0.0), _GOOD_C2W, "Cameras.K: focal lengths must be > 0"),
        (_edit(_GOOD_K, (0, 0), -50.0), _GOOD_C2W, "Cameras.K: focal lengths must be > 0"),
        (_edit(_GOOD_K, (1, 1), 1e20), _GOOD_C2W, r"Cameras.K: focal lengths must be > 0 and at most 1e\+12 px"),
        (_edit(_GOOD_K, (0, 1), 0.5), _GOOD_C2W, r"Cameras.K: must be .* \(no skew, K\[2, 2\] = 1\)"),
        (_edit(_GOOD_K, (2, 2), 2.0), _GOOD_C2W, r"Cameras.K: must be .*K\[2, 2\] = 1"),
        (_edit(_GOOD_K, (2, 0), 0.1), _GOOD_C2W, "Cameras.K: must be"),
        (_GOOD_K, _POSE * 2, "Cameras.c2w: bottom row must be"),
        (_GOOD_K, _edit(_POSE, (slice(0, 3), slice(0, 3)), _POSE[:3, :3] * 2), "Cameras.c2w: rotation is not orthonormal"),
        (_GOOD_K, _MIRROR, r"Cameras.c2w: rotation is not orthonormal with det \+1 \(max error 2 "),
        (_GOOD_K, _edit(_POSE, (slice(0, 3), slice(0, 3)), 0.0), "Cameras.c2w: rotation is not orthonormal"),
        (_GOOD_K, _edit(_POSE, (0, 1), _POSE[0, 1] + 0.01), "Cameras.c2w: rotation is not orthonormal"),
        (_GOOD_K, _edit(_POSE, (3, 0), 2e-3), "Cameras.c2w: bottom row must be"),
    ],
)
def test_what_no_camera_is_raises_naming_the_field(K, c2w, match):
    with pytest.raises(ValueError, match=match):
        Cameras(K, c2w, W, H)


def test_every_constructor_validates_and_names_the_camera(cams):
    with pytest.raises(ValueError, match="camera 1"):
        cams[0].with_c2w(torch.stack([_POSE, _MIRROR]))
    with pytest.raises(ValueError, match="3 intrinsics but 2 poses"):
        cams.with_c2w(torch.stack([_POSE, _POSE]))
    assert len(cams[0].with_c2w(_POSE)) == 1
    with pytest.raises(ValueError, match="Cameras.K: focal"):
        Cameras.from_intrinsics(0.0, 40.0, W / 2, H / 2, _POSE, W, H)
    with pytest.raises(ValueError, match="Cameras.c2w"):
        Cameras.from_opengl(_GOOD_K, _MIRROR, W, H)


def test_cameras_derived_from_checked_ones_are_not_checked_again(cams, monkeypatch):
    """Indexing checked cameras costs no second check; editing their tensors in place
    through torch or replacing one brings the checks back."""
    calls = []
    monkeypatch.setattr(cameras_module, "_check_rigid", lambda c2w, tolerance: calls.append(len(c2w)))
    one = cams[1]
    assert len(one[0]) == 1 and calls == []
    torch.testing.assert_close(one.c2w, cams.c2w[1:2])
    cams.K[2, 0, 0] = 51.0  # torch moves the version counter: checked again
    cams[0]
    assert calls == [1]
    monkeypatch.undo()
    cams.c2w[2, :3, :3] *= 2
    with pytest.raises(ValueError, match="c2w: rotation is not orthonormal"):
        cams[2]
    cams.K = _edit(cams.K, (0, 0, 0), float("nan"))
    with pytest.raises(ValueError, match="Cameras.K: contains NaN"):
        cams[0]


def test_cameras_of_inference_mode_tensors_are_checked_every_time(cams, monkeypatch):
    """Inference-mode tensors have no version counter to trust: indexing them checks again."""
    with torch.inference_mode():
        frozen = Cameras(cams.K.clone(), cams.c2w.clone(), W, H)
        calls = []
        monkeypatch.setattr(cameras_module, "_check_rigid", lambda c2w, tolerance: calls.append(len(c2w)))
        torch.testing.assert_close(frozen[2].c2w, cams.c2w[2:])
    assert calls == [1]


def test_float32_round_off_of_composed_poses_passes():
    """Hundreds of float32 pose compositions drift by ~1e-6, far inside the tolerance."""
    step = look_at((0.01, 0.02, -1.0), (0.0, 0.0, 0.0)).float()
    pose = torch.eye(4)
    for _ in range(500):
        pose = step @ pose
    Cameras(_GOOD_K.float(), pose, W, H)
    Cameras(_GOOD_K.float(), _POSE.float(), W, H)


def test_opengl_opencv_flip_only_touches_y_and_z_columns():
    c2w = look_at((0.4, 0.5, 0.6), (0.0, 0.0, 0.0))
    gl = opencv_to_opengl(c2w)
    torch.testing.assert_close(gl[:, 0], c2w[:, 0])
    torch.testing.assert_close(gl[:3, 1:3], -c2w[:3, 1:3])
    torch.testing.assert_close(gl[:, 3], c2w[:, 3])
    torch.testing.assert_close(opengl_to_opencv(gl), c2w)
