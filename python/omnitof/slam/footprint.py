"""The ground the robot drove over, free in the written map.

A sensor whose beams never cross the ground it drives over leaves holes along the path: the
mirror rig has no reading straight ahead or behind down a corridor longer than its range and none
along its diagonals, and a missing ToF reading clears nothing (`map.clear_no_echo` stays off), so
every ToF map had a chain of unknown patches some 0.4 m wide, one between each two integrated
scans, down the middle of each corridor it drove (a planner that treats unknown as blocked
cannot follow the robot's own path back). The robot was there, so those cells were free: `map.footprint_radius` marks every cell
whose centre lies within that radius of the trajectory (every scan's pose, the segments between
them included) as free with the map's full confidence (`map.l_min`), as ROS's costmaps clear a
robot's footprint. A cell where the scans found an obstacle (log-odds above 0) keeps it: the
footprint never erases what was seen. Applied once, to the map written at the end; the filter's
own maps are left as the scans made them.
"""

from __future__ import annotations

import math

import numpy as np

from omnitof.types import OccupancyMap

# Cells per chunk of path points (bounds the index arrays on a long log: ~100 MB at most).
_CHUNK = 200_000


def path_cells(xy: np.ndarray, resolution: float, max_segment: float = math.inf) -> np.ndarray:
    """The cells (K, 2) (column, row: floor(xy / resolution)) that the polyline `xy` (N, 2)
    passes through, sampled every half cell along each segment no longer than `max_segment`
    (longer ones, a gap in the log or a jump of the pose, only at their ends: the robot did not
    drive them in a straight line); unique, any order; points that are not finite are left out."""
    xy = np.asarray(xy, dtype=np.float64)
    xy = xy[np.all(np.isfinite(xy), axis=1)]
    if len(xy) == 0:
        return np.zeros((0, 2), dtype=np.int64)
    seg = np.diff(xy, axis=0)
    length = np.hypot(seg[:, 0], seg[:, 1])
    steps = np.where(length <= max_segment, np.maximum(1, np.ceil(length / (0.5 * resolution))), 1).astype(np.int64)
    start = np.repeat(xy[:-1], steps, axis=0)
    frac = (np.arange(int(steps.sum())) - np.repeat(np.cumsum(steps) - steps, steps)) / np.repeat(steps, steps)
    points = np.vstack([start + frac[:, None] * np.repeat(seg, steps, axis=0), xy[-1:]])
    return np.unique(np.floor(points / resolution).astype(np.int64), axis=0)


def disc_offsets(radius: float, resolution: float) -> np.ndarray:
    """Cell offsets (M, 2) whose centres lie within `radius` of the centre of cell (0, 0)."""
    n = int(math.floor(radius / resolution))
    di, dj = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
    inside = np.hypot(di, dj) * resolution <= radius + 1e-9
    return np.stack([di[inside], dj[inside]], axis=1)


def clear_footprint(occ: OccupancyMap, xy: np.ndarray, radius: float, free_log_odds: float) -> OccupancyMap:
    """`occ` with every cell within `radius` (m) of the path `xy` (N, 2) set to `free_log_odds`
    (< 0) and known, unless it holds evidence of an obstacle (log-odds > 0). The grid grows where
    the footprint reaches beyond it. radius 0 returns `occ` itself."""
    if radius <= 0:
        return occ
    res = float(occ.resolution)
    origin = np.asarray(occ.origin, dtype=np.float64)
    # (col, row) in the grid; segments longer than the disc's diameter are not filled in
    cells = path_cells(np.asarray(xy, dtype=np.float64)[:, :2] - origin, res, max_segment=2.0 * radius)
    if len(cells) == 0:
        return occ
    offsets = disc_offsets(radius, res)
    n = int(np.abs(offsets).max())
    h, w = occ.log_odds.shape
    lo_c, lo_r = min(0, int(cells[:, 0].min()) - n), min(0, int(cells[:, 1].min()) - n)
    hi_c, hi_r = max(w, int(cells[:, 0].max()) + n + 1), max(h, int(cells[:, 1].max()) + n + 1)
    log_odds = np.zeros((hi_r - lo_r, hi_c - lo_c), dtype=np.float32)
    known = np.zeros(log_odds.shape, dtype=bool)
    log_odds[-lo_r:-lo_r + h, -lo_c:-lo_c + w] = occ.log_odds
    known[-lo_r:-lo_r + h, -lo_c:-lo_c + w] = occ.known
    footprint = np.zeros(log_odds.shape, dtype=bool)
    for first in range(0, len(cells), _CHUNK):
        chunk = cells[first:first + _CHUNK]
        footprint[(chunk[:, None, 1] + offsets[None, :, 1] - lo_r).ravel(),
                  (chunk[:, None, 0] + offsets[None, :, 0] - lo_c).ravel()] = True
    clear = footprint & ~(known & (log_odds > 0.0))
    log_odds[clear] = free_log_odds
    known |= clear
    return OccupancyMap(log_odds=log_odds, known=known, resolution=occ.resolution,
                        origin=(float(origin[0] + lo_c * res), float(origin[1] + lo_r * res)))
