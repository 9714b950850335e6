"""The benchmarks' chart helper (benchmarks/plotting.py, matplotlib)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
from plotting import Panel, line_panels


def test_line_panels_draws_every_series_in_its_colour(tmp_path):
    colours = {"a": (214, 39, 40), "b": (31, 119, 180)}
    panels = [
        Panel("first", {"a": [(0, 1, "x"), (1, 3, "")], "b": [(0, 2, ""), (1, 50, "clipped")]}, (0, 1), (0, 4),
              [(0, "zero"), (1, "one")], [(0, "0"), (4, "4")]),
        Panel("second", {"a": [(0, 0, "")]}, (-1, 1), (-1, 1)),
    ]  # fmt: skip
    path = tmp_path / "chart.png"
    line_panels(path, panels, colours, note="a note", panel_size=(300, 200))
    image = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert image.shape[1] == 600 and image.shape[0] > 200
    for rgb in colours.values():
        assert (np.abs(image - rgb).sum(-1) < 10).sum() > 50, rgb  # lines, markers and legend


def test_a_stopped_save_keeps_the_old_chart(tmp_path, monkeypatch):
    path = tmp_path / "chart.png"
    path.write_bytes(b"old chart")

    def stopped(self, fname, *args, **kwargs):
        Path(fname).write_bytes(b"\x89PNG half")  # the start of the file, then the process stops
        raise KeyboardInterrupt

    monkeypatch.setattr("matplotlib.figure.Figure.savefig", stopped)
    with pytest.raises(KeyboardInterrupt):
        line_panels(path, [Panel("p", {"a": [(0, 1, "")]}, (0, 1), (0, 2))], {"a": (0, 0, 0)})
    assert path.read_bytes() == b"old chart" and [p.name for p in tmp_path.iterdir()] == ["chart.png"]
