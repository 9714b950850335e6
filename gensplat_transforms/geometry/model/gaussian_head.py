"""DPT-style Gaussian head: intermediate decoder tokens + shallow RGB features -> per-pixel Gaussians.

Four decoder outputs are reassembled into feature maps at 4x, 2x, 1x and 1/2x the patch grid,
fused coarse-to-fine with residual convolution units, resized to the image, concatenated with
shallow full-resolution RGB features and mapped by 1x1 convolutions to the raw attributes.
Activations (the released GenSplat's): opacity = sigmoid, quaternion normalised (eps 1e-8),
scale = 0.001 * softplus clamped at 0.3. SH coefficients are raw; the model adds the pixel's
own colour to the DC term, so an untrained head already reproduces the input colours.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ...core.sh import num_sh_bases


class ResidualConvUnit(nn.Module):
    def __init__(self, c: int):
        super().__init__()
        self.conv1 = nn.Conv2d(c, c, 3, padding=1)
        self.conv2 = nn.Conv2d(c, c, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FusionBlock(nn.Module):
    """out = conv1x1(resize(rcu2(rcu1(x) + coarser))); the coarsest block has no ``coarser`` input
    and no ``rcu1``. ``coarser`` comes already resized to x's size."""

    def __init__(self, c: int, merge: bool):
        super().__init__()
        if merge:
            self.rcu1 = ResidualConvUnit(c)
        self.rcu2 = ResidualConvUnit(c)
        self.out = nn.Conv2d(c, c, 1)

    def forward(self, x: torch.Tensor, coarser: torch.Tensor | None, size: tuple[int, int]) -> torch.Tensor:
        if coarser is not None:
            x = self.rcu1(x) + coarser
        x = self.rcu2(x)
        return self.out(F.interpolate(x, size=size, mode="bilinear", align_corners=False))


class GaussianHead(nn.Module):
    """Per-pixel opacity, quaternion, scales and SH colour of one Gaussian per pixel.

    Args:
        dim: width of the decoder tokens.
        features: DPT feature channels.
        rgb_features: channels of the shallow RGB branch.
        sh_degree: degree of the predicted SH colour.
    """

    def __init__(self, dim: int, features: int, rgb_features: int, sh_degree: int):
        super().__init__()
        self.sh_bases = num_sh_bases(sh_degree)
        self.proj = nn.ModuleList(nn.Linear(dim, features) for _ in range(4))
        self.resample = nn.ModuleList([
            nn.ConvTranspose2d(features, features, 4, stride=4),
            nn.ConvTranspose2d(features, features, 2, stride=2),
            nn.Identity(),
            nn.Conv2d(features, features, 3, stride=2, padding=1),
        ])  # fmt: skip
        self.fusion = nn.ModuleList(FusionBlock(features, merge=i < 3) for i in range(4))
        self.rgb = nn.Sequential(
            nn.Conv2d(3, rgb_features, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(rgb_features, rgb_features, 3, padding=1),
        )
        self.out = nn.Sequential(
            nn.Conv2d(features + rgb_features, features, 1),
            nn.ReLU(),
            nn.Conv2d(features, 8 + 3 * self.sh_bases, 1),
        )
        self._init_output()

    def _init_output(self) -> None:
        """Start near identity rotations, opacity 0.9 and scale 0.005 (a pixel at depth ~1)."""
        last = self.out[-1]
        nn.init.normal_(last.weight, std=1e-3)
        nn.init.zeros_(last.bias)
        with torch.no_grad():
            last.bias[0] = math.log(0.9 / 0.1)
            last.bias[1] = 1.0
            last.bias[5:8] = math.log(math.expm1(5.0))

    def forward(
        self, tokens: list[torch.Tensor], images: torch.Tensor, h: int, w: int
    ) -> dict[str, torch.Tensor]:
        """
        Args:
            tokens: four (N, h*w, dim) patch-token maps, shallow to deep.
            images: (N, 3, H, W) the normalised input images.
            h, w: patch grid.
        Returns:
            opacity (N, H, W); quats (N, H, W, 4) w-x-y-z unit, camera frame; scales (N, H, W, 3);
            sh (N, H, W, K, 3) camera frame, without the pixel colour.
        """
        n, _, H, W = images.shape
        maps = [
            rs(proj(t).transpose(1, 2).reshape(n, -1, h, w))
            for t, proj, rs in zip(tokens, self.proj, self.resample, strict=True)
        ]
        x = None
        for i in (3, 2, 1, 0):
            size = maps[i - 1].shape[-2:] if i > 0 else (4 * h, 4 * w)
            x = self.fusion[i](maps[i], x, size)
        x = F.interpolate(x, size=(H, W), mode="bilinear", align_corners=False)
        raw = self.out(torch.cat([x, self.rgb(images)], dim=1))
        opacity, quats, scales, sh = raw.split([1, 4, 3, 3 * self.sh_bases], dim=1)
        return {
            "opacity": torch.sigmoid(opacity[:, 0]),
            "quats": F.normalize(quats, dim=1, eps=1e-8).permute(0, 2, 3, 1),
            "scales": (0.001 * F.softplus(scales)).clamp(max=0.3).permute(0, 2, 3, 1),
            "sh": sh.reshape(n, self.sh_bases, 3, H, W).permute(0, 3, 4, 1, 2),
        }
