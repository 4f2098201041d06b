"""Run the paper's Rao-Blackwellized particle filter (section IV) over a stream of range scans.

The filter itself (motion sampling, beam-model weights, log-odds maps, resampling) runs in the
Rust core; this module decides which scans to integrate, feeds them, and turns the best
particle's state into a map and a trajectory with a pose for every scan.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from omnitof import _core
from omnitof.slam.config import SlamConfig
from omnitof.geometry import compose, relative
from omnitof.types import OccupancyMap, ScanSequence, Trajectory


@dataclass
class SlamResult:
    """What a SLAM run produces.

    trajectory: the corrected pose at every scan's timestamp. At an integrated scan it is the best
        particle's pose; between integrated scans it is that pose composed with the odometry
        motion since (so every scan of the log has a pose).
    odometry: the raw odometry pose at every scan, for comparison.
    integrated: indices of the scans the filter integrated.
    map: the best particle's occupancy grid.
    stats: counts and timings of the run.
    """

    trajectory: Trajectory
    odometry: Trajectory
    integrated: np.ndarray
    map: OccupancyMap
    stats: dict = field(default_factory=dict)


def select_scans(odometry: np.ndarray, linear: float, angular: float) -> np.ndarray:
    """Indices of the scans to integrate: the first, then each one taken after the robot moved
    more than `linear` metres or turned more than `angular` radians since the last one chosen.
    """
    chosen = [0]
    last = odometry[0]
    # Sequential by nature (each choice depends on the previous one); cheap per scan.
    for i in range(1, len(odometry)):
        d = relative(last, odometry[i])
        if math.hypot(d[0], d[1]) > linear or abs(d[2]) > angular:
            chosen.append(i)
            last = odometry[i]
    return np.asarray(chosen, dtype=np.int64)


def fill_trajectory(odometry: np.ndarray, integrated: np.ndarray, corrected: np.ndarray) -> np.ndarray:
    """A pose for every scan: the last corrected pose composed with the odometry since it."""
    last = np.searchsorted(integrated, np.arange(len(odometry)), side="right") - 1
    if np.any(last < 0):
        raise ValueError("the first scan must be integrated")
    anchor = integrated[last]
    return compose(corrected[last], relative(odometry[anchor], odometry))


def _make_filter(scans: ScanSequence, cfg: SlamConfig) -> "_core.ParticleFilter":
    """The core's filter for a configuration and a sensor. The core takes every section whole,
    as one keyword each, and derives what it needs (radians, ranges capped by the sensor's,
    threads); only the scan selection (`select_scans`) is done here and kept out of it."""
    sections = cfg.model_dump(exclude={"filter": {"linear_update", "angular_update_deg"}})
    return _core.ParticleFilter(
        **sections, angles=scans.scan_angles(0), sensor_pose=scans.sensor_pose, scan_max_range=scans.max_range
    )


def dense_to_map(log_odds: np.ndarray, ix0: int, iy0: int, resolution: float) -> OccupancyMap:
    """An OccupancyMap from the core's dense grid (NaN = unknown; cell (r, c) = (ix0+c, iy0+r))."""
    known = ~np.isnan(log_odds)
    return OccupancyMap(
        log_odds=np.where(known, log_odds, 0.0).astype(np.float32),
        known=known,
        resolution=resolution,
        origin=(ix0 * resolution, iy0 * resolution),
    )


def run_slam(
    scans: ScanSequence,
    cfg: SlamConfig,
    *,
    progress: Callable[[int], None] | None = None,
) -> SlamResult:
    """Run the filter over every scan of `scans`. `progress(n)` is called with the number of
    scans processed since its last call (for a progress bar)."""
    if len(scans) == 0:
        raise ValueError("no scans to process")
    start = time.perf_counter()
    integrated = select_scans(
        scans.odometry, cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg)
    )
    pf = _make_filter(scans, cfg)
    prev = scans.odometry[integrated[0]]
    done = 0
    corrected_scans = []
    for k in integrated:
        cur = scans.odometry[k]
        own = scans.scan_angles(k) if scans.per_scan_geometry else None  # else the filter's
        if pf.step(prev, cur, scans.scan_ranges(k), int(k), angles=own)[2]:
            corrected_scans.append(int(k))
        prev = cur
        if progress is not None:
            progress(int(k) + 1 - done)
            done = int(k) + 1
    if progress is not None and done < len(scans):
        progress(len(scans) - done)
    scan_idx, corrected = pf.best_trajectory()
    assert np.array_equal(scan_idx, integrated)
    poses = fill_trajectory(scans.odometry, integrated, corrected)
    log_odds, ix0, iy0 = pf.best_map()
    unique_tiles, tile_refs = pf.tile_counts()
    stats = {
        "scans": len(scans),
        "integrated": int(len(integrated)),
        "particles": cfg.filter.particles,
        "resamplings": int(pf.resamplings),
        "proposal": cfg.filter.proposal,
        "scanmatch_fallbacks": int(pf.fallbacks),
        "odometry_corrected_scans": corrected_scans,
        "seconds": time.perf_counter() - start,
        "map_tiles_distinct": int(unique_tiles),
        "map_tiles_referenced": int(tile_refs),
        "map_bytes": int(unique_tiles * _core.ParticleFilter.tile_bytes()),
    }
    return SlamResult(
        trajectory=Trajectory(scans.timestamps, poses),
        odometry=Trajectory(scans.timestamps, scans.odometry),
        integrated=integrated,
        map=dense_to_map(log_odds, ix0, iy0, cfg.map.resolution),
        stats=stats,
    )

