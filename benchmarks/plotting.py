"""Line plots for the benchmarks, drawn with matplotlib (the ``bench`` extra)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from gensplat_transforms.core.atomic import atomic_write

RGB = tuple[int, int, int]


@dataclass
class Panel:
    """One plot panel.

    Attributes:
        title: text above the frame.
        series: name -> points (x, y, label); points are joined in order and each label
            ("" for none) is written beside its point.
        x_range, y_range: (lo, hi) data range of the frame; y is clipped to it.
        x_ticks, y_ticks: (value, text) tick marks.
    """

    title: str
    series: dict[str, list[tuple[float, float, str]]]
    x_range: tuple[float, float]
    y_range: tuple[float, float]
    x_ticks: list[tuple[float, str]] = field(default_factory=list)
    y_ticks: list[tuple[float, str]] = field(default_factory=list)


def line_panels(path: Path, panels: list[Panel], colours: dict[str, RGB], note: str = "",
                panel_size: tuple[int, int] = (420, 300), legend_columns: int = 4) -> None:  # fmt: skip
    """Draw ``panels`` side by side with one legend (a line per series name in ``colours``,
    ``legend_columns`` to a row) and an optional ``note`` under it; save the PNG to ``path``
    (``panel_size`` in pixels at 100 dpi), whole or not at all (a stopped save keeps the old file)."""
    dpi = 100
    fig = Figure(figsize=(len(panels) * panel_size[0] / dpi, (panel_size[1] + 110) / dpi), dpi=dpi)
    axes = fig.subplots(1, len(panels), squeeze=False)
    for ax, p in zip(axes[0], panels, strict=True):
        lo, hi = p.y_range
        for name, points in p.series.items():
            xs, ys = [x for x, _, _ in points], [min(max(y, lo), hi) for _, y, _ in points]
            colour = tuple(c / 255 for c in colours[name])
            ax.plot(xs, ys, "o-", color=colour, markersize=4, clip_on=False)
            for x, y, (_, _, label) in zip(xs, ys, points, strict=True):
                if label:
                    ax.annotate(label, (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, color=colour)
        ax.set(title=p.title, xlim=p.x_range, ylim=p.y_range)
        for ticks, set_ticks in ((p.x_ticks, ax.set_xticks), (p.y_ticks, ax.set_yticks)):
            if ticks:
                set_ticks([t for t, _ in ticks], [text for _, text in ticks])
    handles = [Line2D([], [], color=tuple(c / 255 for c in rgb), lw=3) for rgb in colours.values()]
    fig.legend(handles, list(colours), loc="lower left", ncol=legend_columns, frameon=False,
               bbox_to_anchor=(0, 0.04))  # fmt: skip
    if note:
        fig.text(0.01, 0.01, note, fontsize=8)
    fig.tight_layout(rect=(0, 0.08 + 0.05 * (-(-len(colours) // legend_columns)), 1, 1))
    atomic_write(path, lambda tmp: fig.savefig(tmp, format=Path(path).suffix.lstrip(".")))
