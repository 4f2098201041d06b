"""Figures of a calibration: the paper's Fig. 6 side view of the upper edges seen through each
mirror, and the mirror masks."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure

from omnitof.calibration import Calibration
from omnitof.calibration.check import HeightCheck
from omnitof.viz import save_figure


def plot_side_view(path: str | Path, check: HeightCheck, names: Sequence[str], dpi: int = 150):
    """Side view like the paper's Fig. 6: horizontal range against height of the objects'
    points, one colour per mirror, with each mirror's median upper edge drawn (PNG, atomic)."""
    fig = Figure(figsize=(7.0, 4.0), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    horizontal = np.hypot(check.points[:, 0], check.points[:, 1])
    for index, name in enumerate(names):
        sel = check.owners == index
        colour = f"C{index % 10}"
        ax.scatter(horizontal[sel], check.points[sel, 2], s=2, color=colour, label=name)
        if name in check.per_mirror:
            ax.axhline(check.per_mirror[name][0], color=colour, linewidth=0.8)
    ax.set_xlabel("horizontal range [m]")
    ax.set_ylabel("height above floor [m]")
    ax.set_title(f"upper edges per mirror; difference {1000 * check.spread:.1f} mm")
    ax.legend(markerscale=4, fontsize=8)
    return save_figure(fig, path, dpi=dpi)


def plot_calibration_masks(path: str | Path, cal: Calibration) -> Figure:
    """The masks of a calibration: each mirror's pixels in its colour, named, with the polygons
    they were drawn from (PNG, atomic)."""
    fig = Figure(figsize=(6.4, 5.6), dpi=120)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    colours = np.zeros((*cal.labels.shape, 4))
    colours[..., 3] = 1.0
    for k, name in enumerate(cal.names):
        colours[cal.labels == k] = to_rgba(f"C{k % 10}")
        rows, cols = np.nonzero(cal.labels == k)
        if len(rows):
            ax.text(cols.mean(), rows.mean(), name.upper(), ha="center", va="center", fontsize=9,
                    bbox={"facecolor": "white", "alpha": 0.8, "linewidth": 0})
    h, w = cal.labels.shape
    ax.imshow(colours, extent=(-0.5, w - 0.5, h - 0.5, -0.5), interpolation="nearest")
    for k, (name, poly) in enumerate(cal.polygons.items()):
        closed = np.vstack([poly, poly[:1]])
        ax.plot(closed[:, 0], closed[:, 1], color="white", linewidth=1)
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px]")
    ax.set_title(f"mirror masks, {cal.edge_margin_px:g} px edge margin")
    return save_figure(fig, path)
