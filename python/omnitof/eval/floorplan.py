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


def plan_map(segments: np.ndarray, resolution: float, *, margin: float = 1.0) -> OccupancyMap:
    """A floor plan's walls (segments (N, 2, 2) or (N, 4), metres) drawn into an occupancy map:
    every cell a wall passes through occupied, the rest unknown, `margin` metres of border. A
    reference for `eval.map_agreement` (and `omnitof eval map`) where the plan is known."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    if len(seg) == 0 or not np.all(np.isfinite(seg)):
        raise ValueError("a floor plan needs at least one segment of finite coordinates")
    if not (np.isfinite(resolution) and resolution > 0.0):
        raise ValueError(f"resolution must be a positive number of metres, got {resolution!r}")
    # Samples a quarter of a cell apart along each wall: no cell it crosses is skipped but for
    # corners clipped by less than that.
    points = []
    for a, b in seg:
        n = int(np.ceil(np.linalg.norm(b - a) / (0.25 * resolution))) + 1
        t = np.linspace(0.0, 1.0, n)[:, None]
        points.append(a + t * (b - a))
    pts = np.concatenate(points)
    # Cell centres on whole multiples of the resolution: a plan's walls mostly lie on round
    # coordinates, which then fall on centres, not on the cells' edges (half a cell off, always
    # the same way).
    lo = (np.floor((pts.min(axis=0) - margin) / resolution) - 0.5) * resolution
    cols, rows = (np.ceil((pts.max(axis=0) + margin - lo) / resolution).astype(int))
    log_odds = np.zeros((rows, cols), dtype=np.float32)
    known = np.zeros((rows, cols), dtype=bool)
    ij = np.floor((pts - lo) / resolution).astype(int)
    log_odds[ij[:, 1], ij[:, 0]] = 2.0
    known[ij[:, 1], ij[:, 0]] = True
    return OccupancyMap(log_odds=log_odds, known=known, resolution=float(resolution),
                        origin=(float(lo[0]), float(lo[1])))


# --- the floor plan the robot could see, and how much of it the map holds ---------------------


@dataclass(frozen=True)
class WallCoverage:
    """How much of the wall length in the robot's view the map holds (completeness).

    seen_length: metres of wall that some pose saw (within max_range, line of sight).
    mapped_length: metres of that with an occupied cell centre within `tolerance`.
    fraction: mapped_length / seen_length (NaN if nothing was seen).
    mean_distance: mean distance (m) from the seen wall samples to the nearest occupied cell
        centre (inf if the map has no occupied cell).
    """

    seen_length: float
    mapped_length: float
    fraction: float
    mean_distance: float
    tolerance: float

    def to_dict(self) -> dict[str, float]:
        return {k: float(v) for k, v in self.__dict__.items()}


# The most wall samples one call makes (1.6 GB of points): a building's 10 km of wall at 1 mm.
MAX_WALL_SAMPLES = 1e8


def wall_samples(segments: np.ndarray, spacing: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Points every ~`spacing` metres along the walls, at the middles of equal pieces:
    (points (K, 2), length (K,) of wall each stands for, metres)."""
    seg = np.asarray(segments, dtype=np.float64).reshape(-1, 2, 2)
    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing!r}")
    if not np.isfinite(seg).all():
        raise ValueError("wall segments must be finite")
    lengths = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1)
    total = float(np.maximum(np.ceil(lengths / spacing), 1.0).sum())
    if not total <= MAX_WALL_SAMPLES:  # rather than numpy's MemoryError, or a hang
        raise ValueError(
            f"{lengths.sum():.6g} m of wall every {spacing:g} m is {total:.3g} samples, more than "
            f"{MAX_WALL_SAMPLES:.0e}: give a wider spacing"
        )
    counts = np.maximum(np.ceil(lengths / spacing).astype(np.int64), 1)
    owner = np.repeat(np.arange(len(seg)), counts)
    first = np.cumsum(counts) - counts
    t = (np.arange(counts.sum()) - first[owner] + 0.5) / counts[owner]
    points = seg[owner, 0] + t[:, None] * (seg[owner, 1] - seg[owner, 0])
    return points, lengths[owner] / counts[owner]


def visible_wall_samples(
    segments: np.ndarray,
    poses: np.ndarray,
    max_range: float,
    *,
    spacing: float = 0.05,
    occluders: np.ndarray | None = None,
    pose_spacing: float = 0.25,
    slack: float = 0.02,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which wall samples the robot could see from some pose: within max_range of it and with
    a free line of sight (the ray from the pose towards the sample meets no occluder more than
    `slack` metres before it).

    Args:
        segments: (M, 2, 2) the walls to sample (e.g. World.wall_segments()).
        poses: (N, 3) or (N, 2) true robot positions; consecutive positions nearer than
            pose_spacing to the last kept one are skipped (they see the same walls).
        occluders: (P, 2, 2) what blocks the view (e.g. World.segments_at(scan height));
            default the walls themselves.

    Returns:
        (points (K, 2), visible (K,) bool, length (K,) metres each sample stands for).
    """
    from omnitof.sim.laser2d import World2D

    points, length = wall_samples(segments, spacing)
    visible = np.zeros(len(points), dtype=bool)
    blockers = World2D(np.asarray(segments if occluders is None else occluders, dtype=np.float64))
    xy = np.asarray(poses, dtype=np.float64)[:, :2]
    kept: list[np.ndarray] = []
    for p in xy:
        if not kept or np.hypot(*(p - kept[-1])) >= pose_spacing:
            kept.append(p)
    for p in kept:
        offset = points - p
        dist = np.hypot(offset[:, 0], offset[:, 1])
        near = np.flatnonzero((dist <= max_range) & ~visible)
        if len(near) == 0:
            continue
        angles = np.arctan2(offset[near, 1], offset[near, 0])
        hit = blockers.raycast(p[None, :], angles[None, :], max_range=max_range + slack)[0]
        visible[near[hit >= dist[near] - slack]] = True
    return points, visible, length


def wall_coverage(
    occ: OccupancyMap,
    segments: np.ndarray,
    poses: np.ndarray,
    max_range: float,
    *,
    tolerance: float = 0.05,
    threshold: float = 0.65,
    spacing: float = 0.05,
    occluders: np.ndarray | None = None,
) -> WallCoverage:
    """The share of the wall length the robot could see (`visible_wall_samples`) that the map
    holds: seen wall samples with an occupied cell centre within `tolerance` (occupancy >
    threshold). Map and walls must be in one frame."""
    from scipy.spatial import cKDTree

    points, visible, length = visible_wall_samples(
        segments, poses, max_range, spacing=spacing, occluders=occluders
    )
    seen = points[visible]
    seen_length = float(length[visible].sum())
    centres = occupied_cell_centres(occ, threshold)
    if len(seen) == 0:
        return WallCoverage(0.0, 0.0, float("nan"), float("nan"), tolerance)
    if len(centres) == 0:
        return WallCoverage(seen_length, 0.0, 0.0, float("inf"), tolerance)
    d, _ = cKDTree(centres).query(seen)
    mapped = float(length[visible][d <= tolerance].sum())
    return WallCoverage(seen_length, mapped, mapped / seen_length, float(d.mean()), tolerance)
