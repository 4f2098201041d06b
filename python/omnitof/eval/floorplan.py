"""How well an occupancy map agrees with the true walls of a simulated world."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omnitof.types import OccupancyMap


@dataclass(frozen=True)
class WallAgreement:
    """Occupied cells (p > threshold) against the true walls.

    near_fraction: share of occupied cells whose centre lies within `tolerance` of a true wall.
    mean_distance / median_distance: of occupied cell centres to the nearest true wall (m).
    """

    occupied_cells: int
    near_fraction: float
    mean_distance: float
    median_distance: float
    tolerance: float

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


def occupied_cell_centres(occ: OccupancyMap, threshold: float = 0.65) -> np.ndarray:
    """(K, 2) world coordinates of the centres of cells with occupancy probability > threshold."""
    rows, cols = np.nonzero(occ.known & (occ.probability > threshold))
    x = occ.origin[0] + (cols + 0.5) * occ.resolution
    y = occ.origin[1] + (rows + 0.5) * occ.resolution
    return np.column_stack([x, y])


def wall_agreement(
    occ: OccupancyMap,
    distance_to_walls: Callable[[np.ndarray], np.ndarray],
    *,
    tolerance: float = 0.1,
    threshold: float = 0.65,
) -> WallAgreement:
    """Compare the map's occupied cells with true walls given as a distance function."""
    centres = occupied_cell_centres(occ, threshold)
    if len(centres) == 0:
        return WallAgreement(0, 0.0, float("nan"), float("nan"), tolerance)
    d = distance_to_walls(centres)
    return WallAgreement(
        occupied_cells=len(centres),
        near_fraction=float(np.mean(d <= tolerance)),
        mean_distance=float(d.mean()),
        median_distance=float(np.median(d)),
        tolerance=tolerance,
    )
