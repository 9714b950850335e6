"""examples/droid_preview.py on the real DROID sample, at a small size."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from gensplat_transforms.views.perturbation import EVAL_LEVELS

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "droid_preview.py"


def load_example():
    spec = importlib.util.spec_from_file_location("droid_preview", EXAMPLE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_droid_preview_one_row_per_level(droid_dir, tmp_path, monkeypatch):
    example = load_example()
    assert example.DEFAULT_DATA.resolve() == droid_dir.resolve()
    monkeypatch.chdir(tmp_path)  # any working directory: the default --data is found from the script
    out = example.main(["--out", "preview", "--width", "196", "--height", "112", "--tile-width", "196"])

    renders = out["renders"]
    assert renders.shape == (len(EVAL_LEVELS), 3, 112, 196)
    assert torch.isfinite(renders).all()
    assert list(out["levels"]) == list(EVAL_LEVELS)
    assert out["levels"]["none"]["coverage"] > 0.99  # the source camera sees its own surface discs
    assert all(0 < lv["coverage"] <= 1 for lv in out["levels"].values())

    png = tmp_path / "preview" / "droid_preview.png"
    assert png.is_file() and (tmp_path / "preview" / "droid_preview.json").is_file()
    # one band of pictures per level: runs of rows that are mostly picture (not white, not a
    # line of label text) inside the first picture column, after the 110 px of row labels
    grid = np.asarray(Image.open(png).convert("RGB"))
    column = grid[:, 120 : 120 + 150]
    filled = (column < 250).any(axis=2).mean(axis=1) > 0.5
    bands = int(filled[0]) + int(np.sum(filled[1:] & ~filled[:-1]))
    assert bands == len(EVAL_LEVELS)
