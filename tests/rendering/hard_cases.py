"""Hard cases shared by the renderer tests: one Gaussian each (plus the empty scene), and
the same cases with one field at an extreme magnitude."""

import torch

from gensplat_transforms import Gaussians


def one(mean, scale=0.05, quat=(1.0, 0, 0, 0), opacity=0.9) -> Gaussians:
    scales = [scale] * 3 if not isinstance(scale, tuple) else list(scale)
    return Gaussians(
        means=torch.tensor([mean]), quats=torch.tensor([quat]), scales=torch.tensor([scales]),
        opacities=torch.tensor([opacity]), sh=torch.full((1, 4, 3), 0.3),
    )  # fmt: skip


HARD_CASES = {
    "behind_camera": one([0.0, 0.0, -1.0]),
    "at_camera_centre": one([0.0, 0.0, 0.0]),
    "on_near_plane": one([0.0, 0.0, 0.01]),
    "just_past_near_plane": one([0.0, 0.0, 0.0100001], scale=0.001),
    "centre_outside_image": one([1.2, 0.0, 2.0], scale=0.2),
    "far_outside_image": one([1e4, -1e4, 1.0], scale=0.5),
    "on_image_border": one([1.0, 0.8, 2.0], scale=0.03),
    "zero_scale": one([0.1, 0.0, 2.0], scale=0.0),
    "tiny_scale": one([0.1, 0.0, 2.0], scale=1e-20),
    "huge_scale": one([0.0, 0.0, 2.0], scale=1e20),
    "needle": one([0.0, 0.0, 2.0], scale=(1e8, 1e-12, 1e-12), quat=(0.9, 0.1, 0.3, 0.2)),
    "zero_quaternion": one([0.0, 0.0, 2.0], scale=(0.1, 0.02, 0.01), quat=(0.0, 0, 0, 0)),
    "unnormalised_quaternion": one([0.0, 0.0, 2.0], scale=(0.1, 0.02, 0.01), quat=(40.0, 3.0, -7.0, 1.0)),
    "zero_opacity": one([0.0, 0.0, 2.0], opacity=0.0),
    "faint": one([0.0, 0.0, 2.0], scale=0.1, opacity=0.02),  # opacity-aware box < 3 sigma
    "below_alpha_threshold": one([0.0, 0.0, 2.0], opacity=0.003),
    "empty_scene": Gaussians.empty(sh_degree=1),
    "far_away": one([0.0, 0.0, 1e7], scale=1.0),
}

#: factors that take a field far beyond float32's range, to its edge, or to its subnormals
MAGNITUDES = (1e30, 1e300, 1e-300)
#: fields that may take any finite magnitude (opacities live in [0, 1])
SCALABLE_FIELDS = ("means", "quats", "scales", "sh")


def scaled(g: Gaussians, field: str, factor: float, dtype=torch.float64) -> Gaussians:
    """``g`` in ``dtype`` with ``field`` multiplied by ``factor`` in float64, kept within a
    tenth of ``dtype``'s largest value (finite), then cast."""
    t = {k: v.to(dtype) for k, v in g.tensors().items()}
    top = torch.finfo(dtype).max / 10
    t[field] = (g.tensors()[field].double() * factor).clamp(-top, top).to(dtype)
    return Gaussians(**t)
