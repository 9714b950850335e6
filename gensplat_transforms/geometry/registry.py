"""Reconstructors by name: one list for the CLI, the LeRobot settings and user code."""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..weights import DEFAULT_MODEL_DIR
from .base import Reconstructor
from .feedforward import GenSplatReconstructor
from .geometry import GeometryReconstructor
from .monocular import MonocularReconstructor
from .rgbd import RGBDReconstructor

#: name -> factory(spec, device); ``spec`` as in :func:`make_reconstructor`
RECONSTRUCTORS: dict[str, Callable[[dict, torch.device | None], Reconstructor]] = {
    "rgbd": lambda spec, device: RGBDReconstructor(**spec.get("config", {})),
    "geometry": lambda spec, device: GeometryReconstructor(spec.get("model") or DEFAULT_MODEL_DIR, device=device,
                                                           **spec.get("options", {})),
    "gensplat": lambda spec, device: GenSplatReconstructor(spec.get("model") or DEFAULT_MODEL_DIR, device=device,
                                                           **spec.get("options", {})),
    "monocular": lambda spec, device: MonocularReconstructor(_model(spec), device=device, **spec.get("options", {})),
}


def _model(spec: dict) -> str:
    """The MoGe-2 folder the "monocular" reconstructor needs (it has no default weights)."""
    if not spec.get("model"):
        raise ValueError("the monocular reconstructor needs model: a MoGe-2 checkpoint folder (model.pt of "
                         "Ruicheng/moge-2-vits-normal or -vitl-normal, downloaded beforehand)")  # fmt: skip
    return spec["model"]


def make_reconstructor(spec: dict, device: torch.device | str | None = None) -> Reconstructor:
    """The reconstructor a settings dict names.

    ``spec``: ``{"name": "rgbd", "config": {RGBDConfig fields}}``, or ``{"name": "geometry" |
    "gensplat", "model": <weights directory or hub id; default: the shipped small model>,
    "options": {keyword arguments}}``, or ``{"name": "monocular", "model": <MoGe-2 folder>,
    "options": {...}}``. ``device``: where a model runs (default: the CPU).

    Example:
        >>> make_reconstructor({"name": "rgbd", "config": {"sigma_px": 0.5}}).cfg.sigma_px
        0.5
    """
    name = spec.get("name")
    if name not in RECONSTRUCTORS:
        raise ValueError(f"unknown reconstructor {name!r}; available: {sorted(RECONSTRUCTORS)}")
    return RECONSTRUCTORS[name](spec, None if device is None else torch.device(device))
