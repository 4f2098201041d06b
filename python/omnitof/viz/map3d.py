"""Figures of 3D occupancy maps (paper Fig. 11(b)): top and perspective views of the occupied
voxels, and the height colours that the PLY output shares."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from omnitof.map3d.voxels import DEFAULT_RESOLUTION
from omnitof.viz import save_figure


def height_colors(
    points: np.ndarray, cmap: str = "viridis", z_range: tuple[float, float] | None = None
) -> np.ndarray:
    """(N, 3) uint8 RGB colours of points (N, 3) by height z (low dark, high bright), over
    z_range (default: the points' own range)."""
    import matplotlib

    pts = _points(points)
    lo, hi = z_range if z_range is not None else (_z_range(pts))
    t = np.clip((pts[:, 2] - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    rgba = matplotlib.colormaps[cmap](t)
    return np.round(rgba[:, :3] * 255.0).astype(np.uint8)


def plot_voxels(
    path: str | Path,
    points: np.ndarray,
    *,
    resolution: float = DEFAULT_RESOLUTION,
    trajectory: np.ndarray | None = None,
    title: str = "",
    z_limits: tuple[float, float] | None = None,
    max_points_3d: int = 40_000,
    dpi: int = 120,
) -> Figure:
    """Draw occupied voxel centres (N, 3) as a PNG at `path` (atomically): left, the top view,
    each column of voxels coloured by its highest occupied voxel; right, a perspective view of
    the voxels coloured by height (at most max_points_3d, an even subsample), its height
    exaggerated (and the factor shown) where the map is much wider than high. `trajectory`
    (K, 3) poses (x, y, θ) is drawn on the top view. `z_limits` (zmin, zmax) metres draws only
    the voxels between (e.g. without the floor and ceiling layers)."""
    pts = _points(points)
    if z_limits is not None:
        pts = pts[(pts[:, 2] >= z_limits[0]) & (pts[:, 2] <= z_limits[1])]
    fig = Figure(figsize=(14.0, 6.5), dpi=dpi)
    FigureCanvasAgg(fig)
    top = fig.add_subplot(1, 2, 1)
    side = fig.add_subplot(1, 2, 2, projection="3d")
    zlo, zhi = _z_range(pts)
    if len(pts):
        ij = np.floor(pts[:, :2] / resolution).astype(np.int64)
        i0, j0 = ij.min(axis=0)
        ni, nj = ij.max(axis=0) - (i0, j0) + 1
        image = np.full((nj, ni), np.nan)
        order = np.argsort(pts[:, 2], kind="stable")  # the highest voxel of a column wins
        image[ij[order, 1] - j0, ij[order, 0] - i0] = pts[order, 2]
        extent = (i0 * resolution, (i0 + ni) * resolution, j0 * resolution, (j0 + nj) * resolution)
        shown = top.imshow(image, origin="lower", extent=extent, cmap="viridis", vmin=zlo, vmax=zhi,
                           interpolation="nearest")
        fig.colorbar(shown, ax=top, label="highest occupied voxel z [m]", shrink=0.8)
        step = max(1, math.ceil(len(pts) / max_points_3d))
        sub = pts[::step]
        side.scatter(
            sub[:, 0], sub[:, 1], sub[:, 2], c=sub[:, 2], cmap="viridis", vmin=zlo, vmax=zhi,
            s=2.0, marker="s", linewidths=0, depthshade=False,
        )
        span = np.maximum(pts.max(axis=0) - pts.min(axis=0), resolution)
        exaggeration = max(1.0, 0.2 * float(span[:2].max()) / float(span[2]))
        side.set_box_aspect((span[0], span[1], span[2] * exaggeration))
        side.zaxis.set_major_locator(MaxNLocator(3))
        if exaggeration > 1.05:
            side.set_title(f"perspective view (height ×{exaggeration:.1f})")
    if trajectory is not None:
        traj = np.asarray(trajectory, dtype=np.float64).reshape(-1, 3)
        top.plot(traj[:, 0], traj[:, 1], color="red", linewidth=1.2, label="trajectory")
        top.legend(loc="best")
    top.set_aspect("equal")
    top.set_xlabel("x [m]")
    top.set_ylabel("y [m]")
    top.set_title("top view")
    side.set_xlabel("x [m]")
    side.set_ylabel("y [m]")
    side.set_zlabel("z [m]")
    side.view_init(elev=35.0, azim=-60.0)
    if not side.get_title():
        side.set_title("perspective view")
    fig.suptitle(title or f"{len(pts)} occupied voxels of {resolution:g} m")
    return save_figure(fig, path, dpi=dpi, tight_layout=False)


def _points(array: np.ndarray) -> np.ndarray:
    pts = np.ascontiguousarray(array, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
    return pts


def _z_range(pts: np.ndarray) -> tuple[float, float]:
    if len(pts) == 0:
        return 0.0, 1.0
    lo, hi = float(pts[:, 2].min()), float(pts[:, 2].max())
    return (lo, hi) if hi > lo else (lo, lo + 1.0)
