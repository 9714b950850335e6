"""Line plots with PIL for the benchmarks (matplotlib is not installed here)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from PIL import Image, ImageDraw, ImageFont

RGB = tuple[int, int, int]


@dataclass
class Panel:
    """One plot panel.

    Attributes:
        title: text above the frame.
        series: name -> points (x, y, label); points are joined in order and each label
            ("" for none) is written beside its point.
        x_range, y_range: (lo, hi) data range of the frame.
        x_ticks, y_ticks: (value, text) tick marks.
    """

    title: str
    series: dict[str, list[tuple[float, float, str]]]
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    x_ticks: list[tuple[float, str]] = field(default_factory=list)
    y_ticks: list[tuple[float, str]] = field(default_factory=list)


def _frame_map(p: Panel, x0: float, y0: float, w: float, h: float):
    """(x, y) data -> pixel coordinates in the frame whose top-left corner is (x0, y0) and size
    w x h; y is clipped to the panel's range."""
    (xl, xh), (yl, yh) = p.x_range, p.y_range

    def at(x: float, y: float) -> tuple[float, float]:
        return x0 + (x - xl) / (xh - xl) * w, y0 + h - (min(max(y, yl), yh) - yl) / (yh - yl) * h

    return at


def line_panels(path: Path, panels: list[Panel], colours: dict[str, RGB], note: str = "",
                panel_size: tuple[int, int] = (420, 300)) -> None:  # fmt: skip
    """Draw ``panels`` side by side with one legend (a line per series name in ``colours``)
    and an optional ``note`` under it; save the PNG to ``path``."""
    pw, ph = panel_size
    margin = 50
    legend_rows = -(-len(colours) // 4)
    img = Image.new("RGB", (len(panels) * pw + 40, ph + 2 * margin + 22 * legend_rows + 30), "white")
    draw = ImageDraw.Draw(img)
    draw.font = ImageFont.load_default(size=13)
    small = ImageFont.load_default(size=10)
    for i, p in enumerate(panels):
        x0, y0 = 20 + i * pw + margin, margin
        w, h = pw - margin - 20, ph - margin
        at = _frame_map(p, x0, y0, w, h)
        xl, yl = p.x_range[0], p.y_range[0]
        draw.rectangle([x0, y0, x0 + w, y0 + h], outline="black")
        draw.text((x0, y0 - 22), p.title, fill="black")
        for t, text in p.y_ticks:
            y = at(xl, t)[1]
            draw.line([x0 - 4, y, x0, y], fill="black")
            draw.text((x0 - 6, y), text, fill="black", anchor="rm")
        for t, text in p.x_ticks:
            x = at(t, yl)[0]
            draw.line([x, y0 + h, x, y0 + h + 4], fill="black")
            draw.text((x, y0 + h + 6), text, fill="black", anchor="ma")
        for name, points in p.series.items():
            pts = [at(x, y) for x, y, _ in points]
            if len(pts) > 1:
                draw.line(pts, fill=colours[name], width=2)
            for (x, y), (_, _, label) in zip(pts, points):
                draw.ellipse([x - 3, y - 3, x + 3, y + 3], fill=colours[name])
                if label:
                    draw.text((x + 4, y - 12), label, fill=colours[name], font=small)
    for j, name in enumerate(colours):
        x, y = 20 + margin + (j % 4) * 170, ph + margin + 22 + 22 * (j // 4)
        draw.line([x, y + 6, x + 20, y + 6], fill=colours[name], width=3)
        draw.text((x + 25, y), name, fill="black")
    if note:
        draw.text((20 + margin, ph + margin + 22 * legend_rows + 28), note, fill="black")
    img.save(path)
