"""Figures of the sensor: the mirror regions in the image (paper Fig. 3) and the trade-offs of a
design sweep."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import to_rgba
from matplotlib.figure import Figure

from omnitof.sensor.camera import Camera
from omnitof.sensor.design import SweepRow, sweep_groups
from omnitof.sensor.mirrors import Mirror, MirrorParameterError, interior_pixel, masks
from omnitof.viz import save_figure


def plot_mirror_regions(
    path: str | Path,
    camera: Camera,
    mirrors: Sequence[Mirror],
    image: np.ndarray | None = None,
    *,
    edge_margin_px: float = 2.0,
    title: str = "",
    dpi: int = 150,
) -> Figure:
    """Draw the mirror masks like the paper's Fig. 3 and write them as a PNG (atomically).

    Each mirror's region (from `masks`) is filled with its colour (matplotlib's "C<index>")
    and labelled with its name at its most interior pixel; pixels left out stay black. With
    `image` ((H, W) amplitude or depth, NaN allowed) the regions are drawn translucent over it
    in grey. Axes are pixel columns and rows (u, v), v growing downwards as in the image.

    Returns:
        The matplotlib Figure (Agg canvas, no pyplot).
    """
    labels = masks(camera, mirrors, edge_margin_px)
    fig = Figure(figsize=(6.4, 6.4 * camera.height / camera.width + 0.6), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    extent = (-0.5, camera.width - 0.5, camera.height - 0.5, -0.5)  # pixel edges, v down
    colours = np.zeros((*camera.shape, 4))
    colours[..., 3] = 1.0  # opaque black where no mirror is kept
    for index in range(len(mirrors)):
        colours[labels == index] = to_rgba(f"C{index % 10}")
    if image is not None:
        grey = np.asarray(image, dtype=np.float64)
        if grey.shape != camera.shape:
            raise MirrorParameterError(f"image must have shape {camera.shape}, got {grey.shape}")
        ax.imshow(grey, cmap="gray", extent=extent, interpolation="nearest")
        colours[..., 3] = np.where(labels >= 0, 0.35, 0.0)
    ax.imshow(colours, extent=extent, interpolation="nearest")
    for index, mirror in enumerate(mirrors):
        spot = interior_pixel(labels == index)
        if spot is not None:
            ax.text(spot[1], spot[0], mirror.name.upper(), ha="center", va="center",
                    fontsize=9, bbox={"facecolor": "white", "alpha": 0.8, "linewidth": 0})
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px]")
    ax.set_title(title or f"mirror regions, {edge_margin_px:g} px edge margin")
    return save_figure(fig, path, dpi=dpi)


def plot_sweep(
    path: str | Path, rows: Sequence[SweepRow], *, title: str = "", dpi: int = 120
) -> Figure:
    """Draw the trade-off of a sweep against tilt and write it as a PNG (atomically).

    Four panels share the tilt axis: coverage within the elevation band, coverage at any
    elevation, pixels per degree of bearing, and the elevation range (min to max, with the
    median as a line). One curve per (lens, mirror count, yaw): colour by lens and mirror
    count, line style by yaw.

    Returns:
        The matplotlib Figure (Agg canvas, no pyplot).
    """
    fig = Figure(figsize=(11.0, 8.0), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(2, 2, sharex=True)
    groups = sweep_groups(rows)
    styles = ["-", "--", ":", "-."]
    yaws = sorted({r.yaw_deg for r in rows})
    colours = {key[:2]: f"C{i % 10}" for i, key in enumerate(dict.fromkeys(k[:2] for k in groups))}
    for (lens, count, yaw), group in groups.items():
        tilt = np.array([r.tilt_deg for r in group])
        style = {
            "color": colours[(lens, count)],
            "linestyle": styles[yaws.index(yaw) % len(styles)],
            "label": f"{lens}, {count} mirrors, yaw {yaw:g}°",
        }
        axes[0, 0].plot(tilt, [100 * r.coverage for r in group], **style)
        axes[0, 1].plot(tilt, [100 * r.coverage_any_elevation for r in group], **style)
        axes[1, 0].plot(tilt, [r.pixels_per_degree for r in group], **style)
        axes[1, 1].plot(tilt, [r.median_elevation_deg for r in group], **style)
        axes[1, 1].fill_between(
            tilt, [r.elevation_min_deg for r in group], [r.elevation_max_deg for r in group],
            color=style["color"], alpha=0.08,
        )
    axes[0, 0].set_ylabel("bearings seen in the elevation band [%]")
    axes[0, 1].set_ylabel("bearings seen at any elevation [%]")
    axes[1, 0].set_ylabel("in-band pixels per degree of bearing")
    axes[1, 1].set_ylabel("elevation: median, min–max [deg]")
    axes[1, 1].axhline(0.0, color="black", linewidth=0.8)
    for ax in axes[1]:
        ax.set_xlabel("mirror tilt from the optical axis [deg]")
    for ax in axes.ravel():
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="best")
    fig.suptitle(title or "mirror pyramid design sweep")
    return save_figure(fig, path, dpi=dpi)
