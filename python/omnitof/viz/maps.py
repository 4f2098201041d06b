"""PNG figures of occupancy maps and trajectories, drawn without a display.

The figures use matplotlib's object API (`Figure` + the Agg canvas) rather than pyplot, so
drawing never selects a global backend, opens a window or keeps figures alive in pyplot's registry.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.collections import LineCollection
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from omnitof.viz import save_figure
from omnitof.types import OccupancyMap

UNKNOWN_SHADE = 0.5  # mid-grey for cells never observed
DEFAULT_FIGSIZE = (8.0, 8.0)  # inches; the PNG is figsize * dpi pixels
MAX_DRAWN_CELLS = 3000  # larger maps are drawn by blocks (about twice the figure's pixels)


def map_shades(occ: OccupancyMap) -> np.ndarray:
    """Grey level per cell in [0, 1], row 0 = lowest y: 1 - p for known cells (occupied black,
    free white), UNKNOWN_SHADE where never observed."""
    return np.where(np.asarray(occ.known, dtype=bool), 1.0 - occ.probability, UNKNOWN_SHADE)


def plot_map(
    path: str | Path,
    occ: OccupancyMap | None,
    trajectories: Mapping[str, np.ndarray],
    *,
    title: str = "",
    dpi: int = 150,
    figsize: tuple[float, float] = DEFAULT_FIGSIZE,
) -> Figure:
    """Draw the map and trajectories and write them as a PNG at `path` (atomically).

    Args:
        path: the PNG file.
        occ: the map, drawn in greyscale in metres (None for trajectories only).
        trajectories: name -> (N, 3) poses (x, y, theta) in the map frame, metres; each becomes a
            coloured line (colours in the order of the dict) with a circle at its first pose and
            its name in the legend. With a map, where a trajectory reaches further than a
            quarter of the map's size beyond it (wheel odometry that drifts hundreds of metres
            would shrink the map to a corner of the figure), the view is the map's extent, and
            each trajectory that leaves it is cut at its edge and says so in the legend.
        title: the figure title.
        dpi: resolution; the PNG is figsize[0] * dpi by figsize[1] * dpi pixels.
        figsize: (width, height) in inches.

    Returns:
        The drawn Figure (its axes' transforms map metres to the PNG's pixels, y up).
    """
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    tracks = {name: _poses(name, poses) for name, poses in trajectories.items()}
    view = None
    if occ is not None:
        _draw_map(ax, occ)
        if occ.log_odds.size and any(_beyond(xy, occ.extent, MAX_OVERHANG) for xy in tracks.values()):
            view = occ.extent
    for index, (name, xy) in enumerate(tracks.items()):
        if view is not None and _beyond(xy, view, 0.0):
            name = f"{name} (leaves the map's extent)"
        _draw_trajectory(ax, name, xy, color=f"C{index}")
    if view is not None:
        ax.set_xlim(view[0], view[1])
        ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal", adjustable="datalim" if occ is None else "box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    if trajectories:
        ax.legend(loc="best")
    save_figure(fig, path, dpi=dpi, tight_layout=False)
    return fig


def plot_pose_graph(
    path: str | Path,
    occ: OccupancyMap,
    nodes: np.ndarray,
    closures: np.ndarray,
    rejected: np.ndarray | None = None,
    *,
    relocalised: np.ndarray | None = None,
    title: str = "",
    dpi: int = 150,
    figsize: tuple[float, float] = DEFAULT_FIGSIZE,
) -> Figure:
    """Draw the pose graph over the map as a PNG at `path` (atomically): the nodes (K, 3) joined
    in order by the front end's edges, the accepted loop closures (pairs of node indices (C, 2))
    in green and the rejected ones in red; `relocalised` (node indices): where the odometry check
    relocalised the robot onto an older map (the back end's verdict), in orange."""
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    _draw_map(ax, occ)
    nodes = np.asarray(nodes, dtype=np.float64).reshape(-1, 3)
    ax.plot(nodes[:, 0], nodes[:, 1], color="C0", linewidth=0.8, label=f"nodes ({len(nodes)})")
    ax.plot(nodes[:, 0], nodes[:, 1], ".", color="C0", markersize=2)
    for pairs, colour, name in ((closures, "green", "loop closures"), (rejected, "red", "rejected closures")):
        pairs = np.zeros((0, 2), dtype=np.int64) if pairs is None else np.asarray(pairs).reshape(-1, 2)
        if len(pairs):
            segments = np.stack([nodes[pairs[:, 0], :2], nodes[pairs[:, 1], :2]], axis=1)
            ax.add_collection(LineCollection(segments, colors=colour, linewidths=0.6, alpha=0.7,
                                             label=f"{name} ({len(pairs)})"))
    moved = np.zeros(0, dtype=np.int64) if relocalised is None else np.asarray(relocalised, dtype=np.int64).ravel()
    if len(moved):
        ax.plot(nodes[moved, 0], nodes[moved, 1], "^", color="C1", markersize=6,
                label=f"relocalisations ({len(moved)})")
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or "pose graph")
    ax.legend(loc="best")
    return save_figure(fig, path, dpi=dpi, tight_layout=False)


def _draw_map(ax: Axes, occ: OccupancyMap) -> None:
    if occ.log_odds.size == 0:
        return  # no cell to draw: an image of zero extent would only make matplotlib warn
    # origin="lower": row 0 of the grid is the lowest y. "nearest" keeps cells crisp.
    ax.imshow(
        _at_most(map_shades(occ), MAX_DRAWN_CELLS),
        cmap="gray",
        vmin=0.0,
        vmax=1.0,
        origin="lower",
        extent=occ.extent,
        interpolation="nearest",
    )


def _at_most(shades: np.ndarray, cells: int) -> np.ndarray:
    """Shades of a map with more than `cells` cells on a side, reduced by whole k×k blocks to
    their darkest cell (so thin walls stay visible): matplotlib would otherwise resample the
    full array, gigabytes for a map of hundreds of metres, for a figure of a thousand pixels."""
    k = -(-max(shades.shape) // cells)
    if k <= 1:
        return shades
    h, w = shades.shape
    padded = np.full((-(-h // k) * k, -(-w // k) * k), UNKNOWN_SHADE)
    padded[:h, :w] = shades
    return padded.reshape(padded.shape[0] // k, k, padded.shape[1] // k, k).min(axis=(1, 3))


# Trajectories that reach further than this share of the map's width or height beyond it are cut
# at the map's edge; nearer ones are drawn whole, the figure grown to hold them.
MAX_OVERHANG = 0.25


def _beyond(poses: np.ndarray, extent: tuple[float, float, float, float], share: float) -> bool:
    """Whether a finite pose of `poses` (N, 3) lies further outside `extent` (x0, x1, y0, y1)
    than `share` of its width (in x) or height (in y)."""
    x0, x1, y0, y1 = extent
    mx, my = share * (x1 - x0), share * (y1 - y0)
    x, y = poses[:, 0], poses[:, 1]
    return bool(np.any((x < x0 - mx) | (x > x1 + mx) | (y < y0 - my) | (y > y1 + my)))


def _poses(name: str, poses: np.ndarray) -> np.ndarray:
    xy = np.asarray(poses, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] != 3:
        raise ValueError(f"trajectory '{name}' must be (N, 3) poses, got shape {xy.shape}")
    return xy


def _draw_trajectory(ax: Axes, name: str, xy: np.ndarray, *, color: str) -> None:
    """One trajectory (N, 3) as a line, a circle at its first pose."""
    ax.plot(xy[:, 0], xy[:, 1], color=color, linewidth=1.5, label=name)
    if len(xy):
        ax.plot(xy[0, 0], xy[0, 1], marker="o", color=color, markersize=6, linestyle="none")


def plot_map_agreement(
    path: str | Path,
    reference: OccupancyMap,
    cells: np.ndarray,
    distance: np.ndarray,
    tolerance: float,
    *,
    title: str = "",
    dpi: int = 150,
    figsize: tuple[float, float] = DEFAULT_FIGSIZE,
) -> Figure:
    """Draw a reference map (grey) and an estimate's occupied cells moved into its frame ((K, 2)
    metres, `omnitof.eval.map_agreement`), each coloured by its distance to the reference's
    nearest occupied cell (K,) up to 4·tolerance, as a PNG at `path`."""
    cells = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
    distance = np.asarray(distance, dtype=np.float64).reshape(-1)
    if len(cells) != len(distance):
        raise ValueError(f"{len(cells)} cells need as many distances, got {len(distance)}")
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    _draw_map(ax, reference)
    # Nearest last, so that the walls that agree are not hidden under the ones that do not.
    order = np.argsort(-distance, kind="stable")
    dots = ax.scatter(cells[order, 0], cells[order, 1], c=distance[order], s=1.5, marker="s", linewidths=0,
                      cmap="plasma", vmin=0.0, vmax=4.0 * tolerance)
    fig.colorbar(dots, ax=ax, label="distance to the reference's walls [m]", fraction=0.046, pad=0.04, extend="max")
    x0, x1, y0, y1 = reference.extent
    if len(cells):
        x0, x1 = min(x0, cells[:, 0].min()), max(x1, cells[:, 0].max())
        y0, y1 = min(y0, cells[:, 1].min()), max(y1, cells[:, 1].max())
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    share = float(np.mean(distance <= tolerance)) if len(distance) else float("nan")
    ax.set_title(title or "map against reference")
    ax.text(0.01, 0.01, f"{100 * share:.1f} % of {len(cells)} occupied cells within {100 * tolerance:g} cm",
            transform=ax.transAxes, fontsize=8, va="bottom")
    return save_figure(fig, path, dpi=dpi)


def plot_trajectory_errors(
    path: str | Path,
    estimate: np.ndarray,
    truth: np.ndarray,
    *,
    title: str = "",
    dpi: int = 150,
    figsize: tuple[float, float] = DEFAULT_FIGSIZE,
) -> Figure:
    """Draw a ground truth and an estimate paired with it pose by pose ((N, 3) each, the
    estimate already aligned, `omnitof.eval.ate`) as a PNG at `path`: the truth grey, the
    estimate coloured by its position error (metres, colour bar)."""
    estimate = _poses("estimate", estimate)
    truth = _poses("truth", truth)
    if estimate.shape != truth.shape:
        raise ValueError(f"the estimate's {len(estimate)} poses must pair with as many of the truth, got {len(truth)}")
    fig = Figure(figsize=figsize, dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot(truth[:, 0], truth[:, 1], color="0.6", linewidth=2.0, label="truth")
    error = np.hypot(estimate[:, 0] - truth[:, 0], estimate[:, 1] - truth[:, 1])
    if len(estimate) > 1:
        segments = np.stack([estimate[:-1, :2], estimate[1:, :2]], axis=1)
        lines = LineCollection(segments, cmap="viridis", linewidths=1.5, label="estimate")
        lines.set_array(0.5 * (error[:-1] + error[1:]))
        ax.add_collection(lines)
        fig.colorbar(lines, ax=ax, label="position error [m]", shrink=0.8)
    ax.plot(estimate[:1, 0], estimate[:1, 1], "o", color="C0", markersize=6, label="start")
    ax.set_aspect("equal", adjustable="datalim")
    ax.autoscale_view()
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title or "trajectory error")
    ax.legend(loc="best")
    return save_figure(fig, path, dpi=dpi)
