"""Saving images and labelled image grids (PNG) for previews."""

from __future__ import annotations

from pathlib import Path

import torch
from PIL import Image, ImageDraw
from torchvision.utils import make_grid

from .atomic import atomic_write


def to_uint8(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    return (image.detach().float().clamp(0, 1) * 255 + 0.5).to(torch.uint8).permute(1, 2, 0).cpu()


def save_grid(
    rows: list[list[torch.Tensor]],
    path: str | Path,
    row_labels: list[str] | None = None,
    col_labels: list[str] | None = None,
    pad: int = 4,
) -> None:
    """Save a grid of (3, H, W) images (all the same size; ``torchvision.utils.make_grid``,
    white padding and gaps for short rows) with optional text labels above and to the left,
    atomically (:func:`.atomic.atomic_write`) in the format the suffix of ``path`` names."""
    h, w = rows[0][0].shape[-2:]
    left = 110 if row_labels else 0
    top = 18 if col_labels else 0
    ncol = max(len(r) for r in rows)
    blank = torch.ones(3, h, w)
    cells = [img.detach().float().cpu() for row in rows for img in [*row, *[blank] * (ncol - len(row))]]
    grid = make_grid(cells, nrow=ncol, padding=pad, pad_value=1.0)
    canvas = Image.new("RGB", (left + grid.shape[-1], top + grid.shape[-2]), "white")
    canvas.paste(Image.fromarray(to_uint8(grid).numpy()), (left, top))
    draw = ImageDraw.Draw(canvas)
    for j, label in enumerate(col_labels or []):
        draw.text((left + pad + j * (w + pad), 3), label, fill="black")
    for i, label in enumerate(row_labels or []):
        for k, line in enumerate(label.split("\n")):
            draw.text((4, top + pad + i * (h + pad) + 4 + 12 * k), line, fill="black")
    image_format = Image.registered_extensions()[Path(path).suffix.lower()]
    atomic_write(path, lambda tmp: canvas.save(tmp, format=image_format))
