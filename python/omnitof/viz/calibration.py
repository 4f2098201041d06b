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
    ax.set_title(f"upper edges per mirror; difference {1000 * check.spread:.1f} mm" if check.measured
                 else "upper edges per mirror; fewer than two mirrors saw one")
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


def plot_board_plan(path: str | Path, width: int, height: int, outlines: Sequence[np.ndarray],
                    first_corners: np.ndarray, dpi: int = 110, taken: Sequence[np.ndarray] = ()) -> Figure:
    """Where each planned checkerboard should appear in the image: one small panel per board
    with the camera's image frame, the board's printed outline (pixels, 4×2 each) and its first
    inner corner (a dot), numbered as in the plan; where boards were already taken, a first
    panel with all their outlines (PNG, atomic)."""
    panels = len(outlines) + (1 if len(taken) else 0)
    cols = min(6, max(1, panels))
    rows = (panels + cols - 1) // cols
    fig = Figure(figsize=(1.9 * cols, 1.65 * rows + 0.4), dpi=dpi)
    FigureCanvasAgg(fig)

    def frame(ax, title: str) -> None:
        ax.set_xlim(-0.5, width - 0.5)
        ax.set_ylim(height - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(title, fontsize=8)

    first = 1
    if len(taken):
        ax = fig.add_subplot(rows, cols, 1)
        for outline in taken:
            closed = np.vstack([outline, outline[:1]])
            ax.plot(closed[:, 0], closed[:, 1], color="0.45", linewidth=0.8)
        frame(ax, f"taken: {len(taken)} boards")
        first = 2
    for k, (outline, corner) in enumerate(zip(outlines, first_corners)):
        ax = fig.add_subplot(rows, cols, first + k)
        closed = np.vstack([outline, outline[:1]])
        ax.fill(closed[:, 0], closed[:, 1], color="C0", alpha=0.35, linewidth=0)
        ax.plot(closed[:, 0], closed[:, 1], color="C0", linewidth=1)
        ax.plot(corner[0], corner[1], "o", color="C3", markersize=3)
        frame(ax, f"board {k:02d}")
    fig.suptitle("planned checkerboard views (image frame; red: the first inner corner)", fontsize=9)
    return save_figure(fig, path, dpi=dpi)
