"""Odometry far from its own origin: the filters run in a frame moved next to the robot.

Odometry in a georeferenced frame (UTM: millions of metres), or from a robot that has driven
for days, puts the robot far from (0, 0). The core's grids address cells by integers within
2^30 of their origin (rust/src/grid.rs, MAX_CELL_INDEX), the back end's submaps within 2^29
(rust/src/loop_closure.rs), so at a fine map.resolution such poses lie beyond them: 5e7 m at
0.01 m is 5e9 cells. Where the odometry reaches beyond ANCHOR_CELLS cells, the filters run on
the scans translated by `-offset`, the first scan's position rounded to whole tiles (16
cells), and every result (trajectory, map origin, pose-graph nodes, voxels) is moved back by
`offset`. The map's cells keep their place in the world, and a translation leaves every
relative motion, so the run is the same up to rounding. Odometry nearer the origin is left as it is: its
results stay bit for bit what they were.

Voxel maps are moved the same way where they reach beyond VOXEL_ANCHOR_CELLS voxels
(`voxel_offset`; omnitof.map3d.voxels keeps its voxels relative to that offset).

Odometry so far out that float64 no longer resolves its motions is refused before the run
(omnitof.slam.limits.check_odometry_precision).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from omnitof.geometry import anchor_offset
from omnitof.slam.limits import TILE_CELLS
from omnitof.types import ScanSequence

# Beyond this many cells from the origin a run is moved: a 64th of the grids' reach, which
# leaves the map around the trajectory, and the submaps' smaller reach, far inside them.
ANCHOR_CELLS = float(2**24)
# The same for voxel maps (the 3D filter's, omnitof.map3d.VoxelMap): a 64th of the ±2^20
# voxels the core's VoxelGrid addresses (rust/src/voxel.rs, INDEX_LIMIT), in whole blocks of 8.
VOXEL_ANCHOR_CELLS = float(2**14)
VOXEL_BLOCK = 8


def run_offset(odometry: np.ndarray, resolution: float) -> np.ndarray:
    """(x, y) metres to move a 2D run by (module notes): zero where the odometry stays within
    ANCHOR_CELLS cells of the origin, else the first pose's position in whole tiles."""
    return anchor_offset(odometry[:, :2], resolution, ANCHOR_CELLS, TILE_CELLS)


def voxel_offset(xy: np.ndarray, resolution: float) -> np.ndarray:
    """(x, y) metres to move a voxel map by whose points (N, 2) lie at `xy` (the 3D filter's
    odometry, a map's first rays): zero within VOXEL_ANCHOR_CELLS voxels of the origin, else
    the first point in whole voxel blocks."""
    return anchor_offset(xy, resolution, VOXEL_ANCHOR_CELLS, VOXEL_BLOCK)


def moved(scans: ScanSequence, offset: np.ndarray) -> ScanSequence:
    """The scans with their odometry translated by -offset (the same object when offset is 0)."""
    if not np.any(offset):
        return scans
    odometry = scans.odometry.copy()
    odometry[:, :2] -= offset
    return dataclasses.replace(scans, odometry=odometry)


def moved_back(poses: np.ndarray, offset: np.ndarray) -> np.ndarray:
    """Poses (N, 3) of the moved run in the odometry's own frame."""
    out = np.array(poses, dtype=np.float64)
    out[:, :2] += offset
    return out
