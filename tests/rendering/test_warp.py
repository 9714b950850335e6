"""Forward warp of RGB-D views: identity, exact pixel shifts, z-buffer, skipped pixels."""

from __future__ import annotations

import torch

from gensplat_transforms.core.cameras import Cameras
from gensplat_transforms.rendering.warp import forward_warp

H, W, F = 24, 32, 40.0


def camera(x: float = 0.0, n: int = 1) -> Cameras:
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[0, 3] = x
    return Cameras.from_intrinsics(F, F, W / 2, H / 2, c2w.expand(n, 4, 4), W, H)


def image(seed: int = 0) -> torch.Tensor:
    return torch.rand(1, 3, H, W, generator=torch.Generator().manual_seed(seed))


def test_warp_into_its_own_camera_is_the_identity():
    img = image()
    depth = 1.0 + torch.rand(1, 1, H, W, generator=torch.Generator().manual_seed(1))
    rgb, mask = forward_warp(img, depth, camera(), camera())
    assert mask.all() and torch.equal(rgb, img)


def test_a_sideways_move_shifts_a_plane_by_whole_pixels():
    img, depth = image(), torch.full((1, 1, H, W), 2.0)
    shift = 3  # F * dx / z pixels
    rgb, mask = forward_warp(img, depth, camera(), camera(x=shift * 2.0 / F, n=2))
    assert rgb.shape == (2, 3, H, W)
    assert torch.equal(rgb[:, :, :, : W - shift], img[:, :, :, shift:].expand(2, -1, -1, -1))
    assert mask[..., : W - shift].all() and not mask[..., W - shift :].any()
    assert (rgb[..., W - shift :] == 0).all()


def test_the_nearest_point_wins_and_pixels_without_depth_are_skipped():
    imgs = torch.cat([torch.zeros(1, 3, H, W), torch.ones(1, 3, H, W)])
    depths = torch.cat([torch.full((1, 1, H, W), 2.0), torch.full((1, 1, H, W), 1.0)])
    depths[1, 0, :, :4] = 0.0  # the near view has no depth there: the far one shows
    depths[0, 0, :, :2] = float("nan")  # neither has: empty
    rgb, mask = forward_warp(imgs, depths, camera(n=2), camera())
    assert (rgb[..., 4:] == 1).all() and (rgb[..., 2:4] == 0).all()
    assert mask[..., 2:].all() and not mask[..., :2].any()
