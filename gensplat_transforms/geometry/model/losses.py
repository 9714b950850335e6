"""Training losses: L = L_rgb + l_depth L_depth + l_3D L_3D + l_cam L_cam (DESIGN.md section 1).

L_rgb uses LPIPS when the caller passes an LPIPS module (its backbone weights are not
available offline); otherwise the perceptual term is 1 - SSIM, so the default runs anywhere.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import kornia
import torch
import torch.nn.functional as F

from ...core.cameras import rigid_inverse
from ...core.config_flags import flag


@dataclass(frozen=True)
class LossWeights:
    """Weights of the training loss L = L_rgb + l_depth L_depth + l_3D L_3D + l_cam L_cam.

    Attributes:
        l1, perceptual: the terms inside L_rgb: L1, and LPIPS when a module is given, else 1 - SSIM.
        depth: l_depth, rendered against predicted depth.
        points: l_3D, the teacher's point maps distilled.
        camera: l_cam, the relative camera poses distilled.
    """

    l1: float = field(default=1.0, metadata=flag("L1 weight inside L_rgb"))
    perceptual: float = field(default=0.2, metadata=flag("SSIM (or LPIPS) weight inside L_rgb"))
    depth: float = field(default=0.1, metadata=flag("weight of the depth distillation loss", flag="--l-depth"))
    points: float = field(default=1.0, metadata=flag("weight of the 3D point-map loss", flag="--l-3d"))
    camera: float = field(default=1.0, metadata=flag("weight of the camera-pose loss", flag="--l-cam"))

    def combine(self, rgb=None, depth=None, points=None, camera=None) -> torch.Tensor:
        """L = L_rgb + depth * L_depth + points * L_3D + camera * L_cam; a term left out (None)
        counts zero. ``camera`` is the (rotation, translation) pair from :func:`camera_loss`."""
        cam = None if camera is None else camera[0] + camera[1]
        weighted = [(1.0, rgb), (self.depth, depth), (self.points, points), (self.camera, cam)]
        present = [w * t for w, t in weighted if t is not None]
        if not present:
            raise ValueError("LossWeights.combine: no loss term given")
        return sum(present)


def rgb_loss(
    pred: torch.Tensor,
    target: torch.Tensor,
    weights: LossWeights = LossWeights(),
    lpips: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] | None = None,
) -> torch.Tensor:
    """L_rgb = l1 * |pred - target|_1 + perceptual * (LPIPS or 1 - SSIM).

    Args:
        pred, target: (N, 3, H, W) rendered and true images in [0, 1].
        lpips: e.g. ``lpips.LPIPS(net="vgg")``; called on images scaled to [-1, 1].
    """
    l1 = (pred - target).abs().mean()
    if lpips is not None:
        perceptual = lpips(2 * pred - 1, 2 * target - 1).mean()
    elif min(pred.shape[-2:]) < 11:
        raise ValueError(f"rgb_loss: images of {tuple(pred.shape[-2:])} are smaller than the 11 px SSIM window")
    else:  # SSIM as metrics.ssim (11x11 Gaussian window, std 1.5, valid windows), in the input dtype
        perceptual = 1 - kornia.metrics.ssim(pred, target, 11, eps=0.0, padding="valid").mean()
    return weights.l1 * l1 + weights.perceptual * perceptual


def depth_loss(
    rendered: torch.Tensor, point_depth: torch.Tensor, mask: torch.Tensor | None = None
) -> torch.Tensor:
    """L_depth: masked mean squared difference between rendered depth and the point map's z.

    Args:
        rendered, point_depth: (...,) depths of the same pixels (e.g. (B, V, H, W)).
        mask: (...,) bool, pixels that count (e.g. rendered alpha > 0.5); None counts all.
    """
    err = (rendered - point_depth) ** 2
    if mask is None:
        return err.mean()
    return (err * mask).sum() / mask.sum().clamp_min(1)


def points_loss(
    pred: torch.Tensor, teacher: torch.Tensor, mask: torch.Tensor | None = None, align_scale: bool = False
) -> torch.Tensor:
    """L_3D: mean squared distance between predicted and teacher camera-frame point maps.

    Args:
        pred, teacher: (B, V, H, W, 3) local point maps.
        mask: (B, V, H, W) bool, valid teacher pixels; None counts all.
        align_scale: first rescale each sample's prediction by the least-squares scale (no
            gradient through it), for scale-free teachers such as Pi3.
    """
    m = torch.ones(pred.shape[:-1], dtype=torch.bool, device=pred.device) if mask is None else mask
    if align_scale:
        w = m[..., None].to(pred.dtype)
        dims = tuple(range(1, pred.ndim))
        s = (w * pred * teacher).sum(dims) / (w * pred * pred).sum(dims).clamp_min(1e-12)
        pred = pred * s.detach().clamp_min(1e-6).reshape(-1, *([1] * (pred.ndim - 1)))
    d2 = ((pred - teacher) ** 2).sum(-1)
    return (d2 * m).sum() / m.sum().clamp_min(1)


def relative_poses(c2w: torch.Tensor) -> torch.Tensor:
    """(B, V, 4, 4) camera-to-world -> (B, V, V, 4, 4) with [i, j] = T_{i<-j} = T_i^-1 T_j."""
    return rigid_inverse(c2w)[:, :, None] @ c2w[:, None, :]


def geodesic_angle(R: torch.Tensor) -> torch.Tensor:
    """Rotation angle (radians, [0, pi]) of (..., 3, 3) rotations; finite gradients at 0."""
    cos = (R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2
    skew = torch.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1
    )
    sin = (skew.square().sum(-1) + 1e-12).sqrt() / 2
    return torch.atan2(sin, cos)


def camera_loss(
    pred: torch.Tensor, teacher: torch.Tensor, huber_delta: float = 0.1, scale: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """L_cam over all ordered pairs i != j of the relative poses T_{i<-j}.

    Rotation: geodesic distance on SO(3) between predicted and teacher relative rotations.
    Translation: Huber between relative translations after aligning the unknown global scale
    (``scale`` per sample, e.g. from the point maps; by default the least-squares scale of the
    relative translations, without gradient). Both are means over the V(V-1) pairs and samples
    (the paper's sum divided by the pair count).

    Args:
        pred, teacher: (B, V, 4, 4) camera-to-world, V >= 2.
    Returns:
        (rotation term, translation term).
    """
    B, V = pred.shape[:2]
    if V < 2:
        raise ValueError(f"camera_loss: needs at least two views, got {V}")
    pred, teacher = pred.float(), teacher.float()
    off = ~torch.eye(V, dtype=torch.bool, device=pred.device)
    rp, rt = relative_poses(pred)[:, off], relative_poses(teacher)[:, off]  # (B, P, 4, 4)
    rot = geodesic_angle(rp[..., :3, :3].transpose(-1, -2) @ rt[..., :3, :3]).mean()
    tp, tt = rp[..., :3, 3], rt[..., :3, 3]
    if scale is None:
        scale = ((tp * tt).sum((1, 2)) / tp.square().sum((1, 2)).clamp_min(1e-12)).detach().clamp_min(1e-6)
    trans = F.huber_loss(scale.reshape(B, 1, 1) * tp, tt, delta=huber_delta)
    return rot, trans
