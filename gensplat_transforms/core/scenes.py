"""A batch of scenes to render in one call: :class:`Scenes`, gsplat's ``[B, N]`` layout.

Both ways the transform makes views build one: a dataloader worker from the reconstructions it
read (:meth:`Scenes.of`, B = the item's stack of timesteps), the batch mode from the depth of a
whole training batch (``RGBDReconstructor.scenes``, B = samples x timesteps).
:func:`.rendering.scenes.render_scenes` draws them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from .cameras import Cameras
from .gaussians import Gaussians
from .views import Reconstruction


@dataclass
class Scenes:
    """B scenes of up to N Gaussians each, padded, with the rig of source cameras each was
    reconstructed from.

    Attributes:
        means (B, N, 3), quats (B, N, 4), scales (B, N, 3), opacities (B, N), sh (B, N, K, 3):
            the Gaussians; padding is where ``keep`` is False (placeholders, never drawn).
        keep: (B, N) bool, the Gaussians each scene has.
        saturation: (B, N) each Gaussian's ``render`` saturation (1: a plain Gaussian).
        sources: the B x V source cameras, scene by scene (the rigs a move turns about), of
            the size the scenes' views are rendered at.
        rays: (B, N, 3) unit directions from the camera that saw each Gaussian to it, or None
            (no ``view_preference``: each camera draws the Gaussians where they are).
        view_preference: see :class:`.views.Reconstruction`; ``render_options``: the other
            ``render`` options the Gaussians are drawn with (e.g. ``dilation``).

    Example: one reconstruction as a batch of one scene
        >>> g = Gaussians(torch.zeros(2, 3), torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 0.05),
        ...               torch.ones(2), torch.ones(2, 1, 3))
        >>> rig = Cameras.from_intrinsics(20.0, 20.0, 8.0, 8.0, torch.eye(4), 16, 16)
        >>> scenes = Scenes.of([Reconstruction(g, rig)])
        >>> scenes.means.shape, len(scenes), scenes.gaussians(0)[0] is g
        (torch.Size([1, 2, 3]), 1, True)
    """

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    sh: torch.Tensor
    keep: torch.Tensor
    saturation: torch.Tensor
    sources: Cameras
    rays: torch.Tensor | None = None
    view_preference: float = 0.0
    render_options: dict | None = None
    #: the reconstructions the scenes were made of (:meth:`of`), whose checked Gaussians are reused
    parts: tuple[Reconstruction, ...] | None = None

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def views(self) -> int:
        """V, the source cameras of each scene."""
        return len(self.sources) // len(self)

    @classmethod
    def of(cls, reconstructions: Sequence[Reconstruction]) -> Scenes:
        """The reconstructions (one per scene; their Gaussians and source rigs alike in dtype,
        camera count, image size and render options but for a per-Gaussian saturation) as
        B = len(reconstructions) scenes; one reconstruction, or several of one size, is not
        copied into padding."""
        recs = tuple(reconstructions)
        if not recs:
            raise ValueError("Scenes.of: no reconstructions")
        first = recs[0]
        options = _options(first)
        for rec in recs[1:]:
            if (_options(rec) != options or rec.view_preference != first.view_preference
                    or (rec.cameras.width, rec.cameras.height, len(rec.cameras)) != (
                        first.cameras.width, first.cameras.height, len(first.cameras))):  # fmt: skip
                raise ValueError("Scenes.of: the reconstructions differ in render options or source cameras")
        n = max(len(r.gaussians) for r in recs)
        prefer = bool(first.view_preference) and all(r.pixel_ids is not None for r in recs)

        def stacked(values: list[torch.Tensor], fill: float) -> torch.Tensor:
            if len(values) == 1:
                return values[0][None]
            return torch.stack([torch.cat([v, v.new_full((n - len(v), *v.shape[1:]), fill)]) if len(v) < n else v
                                for v in values])  # fmt: skip

        gs = [r.gaussians for r in recs]
        keep = torch.stack([torch.arange(n) < len(g) for g in gs]).to(first.gaussians.device)
        return cls(
            stacked([g.means for g in gs], 0.0), stacked([g.quats for g in gs], 0.0),
            stacked([g.scales for g in gs], 0.0), stacked([g.opacities for g in gs], 0.0),
            stacked([g.sh for g in gs], 0.0), keep,
            stacked([_saturation(r) for r in recs], 1.0),
            first.cameras if len(recs) == 1 else Cameras(torch.cat([r.cameras.K for r in recs]),
                                                         torch.cat([r.cameras.c2w for r in recs]),
                                                         first.cameras.width, first.cameras.height),
            stacked([r.rays for r in recs], 0.0) if prefer else None,
            first.view_preference if prefer else 0.0, options, recs,
        )  # fmt: skip

    def gaussians(self, b: int) -> tuple[Gaussians, float | torch.Tensor, torch.Tensor | None]:
        """Scene ``b``'s Gaussians (n,), their saturation (one number, or (n,)) and rays (n, 3)
        or None, without the padding (the reconstruction's own where the scenes were made of
        them)."""
        if self.parts is not None:
            rec = self.parts[b]
            rays = None if self.rays is None else rec.rays
            return rec.gaussians, rec.render_options.get("saturation", 1.0), rays
        keep = self.keep[b]
        t = (self.means[b], self.quats[b], self.scales[b], self.opacities[b], self.sh[b], self.saturation[b])
        if not bool(keep.all()):
            t = tuple(x[keep] for x in t)
        rays = None if self.rays is None else (self.rays[b] if len(t[0]) == keep.numel() else self.rays[b][keep])
        return Gaussians(*t[:5]), t[5], rays


def _options(rec: Reconstruction) -> dict:
    """A reconstruction's render options but its saturation."""
    return {k: v for k, v in rec.render_options.items() if k != "saturation"}


def _saturation(rec: Reconstruction) -> torch.Tensor:
    """(N,) each Gaussian's saturation in a reconstruction (one number spread, 1 when none)."""
    g = rec.gaussians
    value = rec.render_options.get("saturation", 1.0)
    if isinstance(value, torch.Tensor) and value.ndim > 0:
        return value.to(g.opacities)
    return torch.full_like(g.opacities, float(value))
