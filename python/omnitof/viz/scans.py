"""PNG figures of range scans: a polar plot like the paper's Fig. 5(b), the image overlay of the
pixels that fed the slice (for choosing its height), and a map over the true floor plan like
the paper's Figs. 9(b) and 10(b).

Drawn with matplotlib's object API and the Agg canvas (no pyplot, no display), written
atomically.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure

from omnitof.viz import save_figure
from omnitof.types import OccupancyMap
from omnitof.viz.maps import map_shades

if TYPE_CHECKING:
    from omnitof.scan import ScanExtractor


def plot_scan(
    path: str | Path,
    ranges: np.ndarray,
    angles: np.ndarray | None = None,
    *,
    truth: np.ndarray | None = None,
    max_range: float | None = None,
    title: str = "",
    dpi: int = 150,
) -> Figure:
    """Draw one scan as range over bearing on polar axes and write it as a PNG.

    The driving direction (bearing 0) points up and bearings grow counter-clockwise, so the
    robot's left is on the left, as seen from above. Bins without a reading (+inf or NaN) are
    not drawn; their share is given in the title.

    Args:
        ranges: (B,) metres. angles: (B,) radians; default B evenly spaced bins from 0
            (the ScanExtractor's 0°, 1°, ..., 359°).
        truth: (B,) true ranges drawn as a thin line for comparison (inf where none).
        max_range: radial limit of the axes; default the largest finite value.
    """
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    a = np.arange(len(r)) * (2.0 * np.pi / len(r)) if angles is None else np.asarray(angles, float)
    if a.shape != r.shape:
        raise ValueError(f"angles {a.shape} and ranges {r.shape} must match")
    ok = np.isfinite(r)
    fig = Figure(figsize=(6.0, 6.4), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(projection="polar")
    ax.set_theta_zero_location("N")  # type: ignore[attr-defined]
    ax.set_theta_direction(1)  # type: ignore[attr-defined]
    if truth is not None:
        t = np.asarray(truth, dtype=np.float64).reshape(-1)
        if t.shape != r.shape:
            raise ValueError(f"truth {t.shape} and ranges {r.shape} must match")
        t = np.where(np.isfinite(t), t, np.nan)
        ax.plot(np.append(a, a[:1]), np.append(t, t[:1]), color="0.6", linewidth=0.8, label="truth")
    ax.plot(a[ok], r[ok], linestyle="none", marker=".", markersize=3, color="C3", label="range")
    limit = max_range if max_range is not None else (float(r[ok].max()) * 1.05 if ok.any() else 1.0)
    ax.set_ylim(0.0, limit)
    ax.set_title(title or f"range readings, 1° bins ({100.0 * (1.0 - ok.mean()):.0f} % without reading)")
    if truth is not None:
        ax.legend(loc="lower right", fontsize=8)
    save_figure(fig, path, dpi=dpi)
    return fig


def plot_slice_overlay(
    path: str | Path,
    extractor: ScanExtractor,
    distance: np.ndarray,
    amplitude: np.ndarray,
    *,
    title: str = "",
    dpi: int = 150,
) -> Figure:
    """The amplitude image (grey, log scale) with the pixels that fed the slice coloured by
    their horizontal range, and the pixels whose rays could cross the slice at some distance
    tinted; for choosing the slice height and band. Axes are pixel columns and rows (u, v),
    v down, as in the camera image."""
    pts = extractor.slice_points(distance, amplitude)
    amp = np.asarray(amplitude, dtype=np.float64)
    h, w = extractor.shape
    extent = (-0.5, w - 0.5, h - 0.5, -0.5)
    fig = Figure(figsize=(7.0, 7.0 * h / w + 0.8), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    positive = amp[np.isfinite(amp) & (amp > 0)]
    norm = LogNorm(vmin=max(float(positive.min()), 1e-3), vmax=float(positive.max())) if len(positive) else None
    ax.imshow(np.where(amp > 0, amp, np.nan), cmap="gray", norm=norm, extent=extent, interpolation="nearest")
    tint = np.zeros((h, w, 4))
    tint[extractor.candidate_pixels] = (0.2, 0.4, 1.0, 0.18)
    ax.imshow(tint, extent=extent, interpolation="nearest")
    image = np.full((h, w), np.nan)
    image[pts.rows, pts.cols] = pts.ranges
    shown = ax.imshow(image, cmap="viridis", extent=extent, interpolation="nearest",
                      vmin=0.0, vmax=extractor.settings.max_range)
    fig.colorbar(shown, ax=ax, label="horizontal range [m]", shrink=0.8)
    s = extractor.settings
    ax.set_xlabel("u [px]")
    ax.set_ylabel("v [px]")
    ax.set_title(title or f"pixels in the slice {s.height:.2f} ± {s.band:.2f} m: {len(pts.rows)}")
    save_figure(fig, path, dpi=dpi)
    return fig


def plot_floorplan_overlay(
    path: str | Path,
    occ: OccupancyMap,
    walls: np.ndarray,
    *,
    trajectory: np.ndarray | None = None,
    seen_points: np.ndarray | None = None,
    clip_to_map: bool = True,
    title: str = "",
    dpi: int = 150,
    figsize: tuple[float, float] = (8.0, 8.0),
) -> Figure:
    """The map in grey with the true floor plan on top (paper Figs. 9(b), 10(b)).

    Args:
        occ: the map, in the floor plan's frame (map landmarks with `eval.table1.world_to_map`
            or transform the walls first when the map frame differs).
        walls: (M, 2, 2) true wall segments (e.g. `World.wall_segments()`), drawn in red.
        trajectory: (N, 3) poses drawn as a blue line.
        seen_points: (K, 2) wall samples the robot could see, drawn as orange dots under the
            plan (e.g. points[visible] of `eval.floorplan.visible_wall_samples`).
        clip_to_map: limit the axes to the map's extent (a floor plan often covers more).
    """
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.imshow(map_shades(occ), cmap="gray", vmin=0.0, vmax=1.0, origin="lower", extent=occ.extent,
              interpolation="nearest")
    if seen_points is not None and len(seen_points):
        pts = np.asarray(seen_points, dtype=np.float64)
        ax.plot(pts[:, 0], pts[:, 1], linestyle="none", marker=".", markersize=2.0, color="orange",
                alpha=0.7, label="walls in view")
    ax.add_collection(LineCollection(list(np.asarray(walls).reshape(-1, 2, 2)), colors="red", linewidths=0.8,
                                     label="floor plan"))
    if trajectory is not None:
        t = np.asarray(trajectory, dtype=np.float64)
        ax.plot(t[:, 0], t[:, 1], color="C0", linewidth=1.0, label="trajectory")
    ax.set_aspect("equal")
    if clip_to_map:
        x0, x1, y0, y1 = occ.extent
        ax.set_xlim(x0, x1)
        ax.set_ylim(y0, y1)
    else:
        ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or "map and floor plan")
    ax.legend(loc="best", fontsize=8)
    save_figure(fig, path, dpi=dpi)
    return fig
