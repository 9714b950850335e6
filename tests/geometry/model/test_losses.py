"""Training losses on constructed cases."""

import math

import pytest
import torch
from tiny_model import TINY

from gensplat_transforms.core.cameras import Cameras, look_at
from gensplat_transforms.core.metrics import ssim_map
from gensplat_transforms.core.rotations import quat_to_rotmat
from gensplat_transforms.data.scenes import TabletopScene, default_cameras
from gensplat_transforms.geometry.model import GenSplatModel, to_gaussians
from gensplat_transforms.geometry.model.losses import (
    LossWeights,
    camera_loss,
    depth_loss,
    geodesic_angle,
    points_loss,
    rgb_loss,
)
from gensplat_transforms.rendering import render
from gensplat_transforms.views.perturbation import axis_rotation


def rig(b: int = 2, v: int = 3) -> torch.Tensor:
    """(b, v, 4, 4) cameras on a circle looking at the origin."""
    eyes = [(math.cos(a), math.sin(a), 0.8) for a in torch.linspace(0, 2, v).tolist()]
    return torch.stack([look_at(e, (0, 0, 0), dtype=torch.float32) for e in eyes]).expand(b, v, 4, 4).clone()


def test_identical_poses_give_zero_and_finite_gradients():
    poses = rig().requires_grad_(True)
    rot, trans = camera_loss(poses, rig())
    assert rot.item() < 1e-5 and trans.item() < 1e-10
    (rot + trans).backward()
    assert torch.isfinite(poses.grad).all()


def test_a_90_degree_relative_rotation_gives_half_pi():
    teacher = torch.eye(4).repeat(1, 2, 1, 1)
    pred = teacher.clone()
    pred[0, 1, :3, :3] = axis_rotation("y", 90.0, dtype=torch.float32)
    rot, trans = camera_loss(pred, teacher)
    torch.testing.assert_close(rot, torch.tensor(math.pi / 2), atol=1e-5, rtol=0)
    assert trans.item() == 0.0


def test_camera_loss_ignores_the_global_frame_and_scale():
    """Relative poses do not see a global rigid motion, and the scale is aligned."""
    teacher = rig()
    g = torch.eye(4)
    g[:3, :3] = quat_to_rotmat(torch.tensor([0.8, 0.3, -0.2, 0.4]))
    g[:3, 3] = torch.tensor([0.5, -1.0, 2.0])
    pred = g @ teacher
    pred[..., :3, 3] *= 3.0  # a different global scale
    rot, trans = camera_loss(pred, teacher)
    assert rot.item() < 1e-3 and trans.item() < 1e-8


def test_camera_loss_sees_a_wrong_translation():
    teacher = rig()
    pred = teacher.clone()
    pred[:, 1, :3, 3] += torch.tensor([0.3, 0.0, 0.0])
    assert camera_loss(pred, teacher)[1].item() > 1e-4
    with pytest.raises(ValueError, match="two views"):
        camera_loss(teacher[:, :1], teacher[:, :1])


def test_geodesic_angle_matches_the_rotation_angle():
    angles = torch.tensor([0.0, 0.3, 1.0, 2.5, math.pi - 1e-3])
    R = torch.stack([axis_rotation("x", math.degrees(a), dtype=torch.float64) for a in angles.tolist()])
    torch.testing.assert_close(geodesic_angle(R), angles.double(), atol=1e-5, rtol=0)


def test_rgb_loss_l1_and_ssim_fallback():
    torch.manual_seed(0)
    img = torch.rand(2, 3, 32, 32)
    assert rgb_loss(img, img).item() < 1e-6
    assert ssim_map(img, img).mean().item() == pytest.approx(1.0, abs=1e-5)
    assert ssim_map(img, torch.rand_like(img)).mean().item() < 0.2
    shifted = (img + 0.1).clamp(0, 1)
    only_l1 = rgb_loss(shifted, img, LossWeights(perceptual=0.0))
    torch.testing.assert_close(only_l1, (shifted - img).abs().mean())


def test_rgb_loss_uses_a_given_lpips_module():
    calls = []

    def fake_lpips(a, b):
        calls.append((a.min().item(), a.max().item()))
        return torch.full((a.shape[0], 1, 1, 1), 0.5)

    img = torch.rand(1, 3, 16, 16)
    loss = rgb_loss(img, img, LossWeights(l1=1.0, perceptual=2.0), lpips=fake_lpips)
    assert loss.item() == pytest.approx(1.0) and calls and calls[0][0] >= -1 and calls[0][1] <= 1


def test_depth_and_points_losses():
    d = torch.ones(1, 2, 4, 4)
    mask = torch.zeros(1, 2, 4, 4, dtype=torch.bool)
    mask[:, 0] = True
    other = d.clone()
    other[:, 0] += 0.5  # error 0.25 where counted
    other[:, 1] += 10.0  # not counted
    assert depth_loss(other, d, mask).item() == pytest.approx(0.25)
    p = torch.rand(2, 2, 4, 4, 3) + 0.5
    assert points_loss(p, p).item() == 0.0
    assert points_loss(p + torch.tensor([0.0, 0.0, 0.2]), p).item() == pytest.approx(0.04)
    assert points_loss(2 * p, p, align_scale=True).item() < 1e-10


def test_combine_weights_the_terms():
    w = LossWeights(depth=0.5, points=2.0, camera=3.0)
    total = w.combine(
        rgb=torch.tensor(1.0), depth=torch.tensor(2.0), camera=(torch.tensor(1.0), torch.tensor(0.5))
    )
    assert total.item() == pytest.approx(1.0 + 1.0 + 4.5)
    with pytest.raises(ValueError):
        w.combine()


def test_a_few_training_steps_lower_the_loss_on_a_tiny_batch():
    """All four terms against true geometry of the procedural tabletop; the photometric term
    renders the predicted Gaussians from the predicted poses with the true intrinsics."""
    size = 28
    cams = default_cameras(size, size)[:2]
    rgb, depth = TabletopScene(0).render(cams)
    rgb, depth = rgb.float(), depth.float()
    K = cams.K.float()
    v, u = torch.meshgrid(torch.arange(size) + 0.5, torch.arange(size) + 0.5, indexing="ij")
    x = (u - K[:, 0, 2, None, None]) / K[:, 0, 0, None, None] * depth[:, 0]
    y = (v - K[:, 1, 2, None, None]) / K[:, 1, 1, None, None] * depth[:, 0]
    teacher_points = torch.stack([x, y, depth[:, 0]], dim=-1)[None]
    teacher_poses = cams.c2w.float()[None]

    torch.manual_seed(0)
    model = GenSplatModel(TINY).train()
    opt = torch.optim.AdamW(model.parameters(), lr=5e-3)
    weights = LossWeights()
    losses = []
    for _ in range(5):
        out = model(rgb[None])
        g = to_gaussians(out)
        rendered = render(g, Cameras(K, out["camera_poses"][0], size, size), background=(1.0, 1.0, 1.0),
                          backend="reference")  # fmt: skip
        loss = weights.combine(
            rgb=rgb_loss(rendered.rgb, rgb, weights),
            depth=depth_loss(
                rendered.depth[:, 0], out["local_points"][0, ..., 2], rendered.alpha[:, 0] > 0.5
            ),
            points=points_loss(out["local_points"], teacher_points),
            camera=camera_loss(out["camera_poses"], teacher_poses),
        )
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert all(math.isfinite(v) for v in losses)
    assert losses[-1] < 0.95 * losses[0], losses
