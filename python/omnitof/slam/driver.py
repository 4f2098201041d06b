"""Run the paper's Rao-Blackwellized particle filter (section IV) over a stream of range scans.

The filter itself (motion sampling, beam-model weights, log-odds maps, resampling) runs in the
Rust core; this module decides which scans to integrate, feeds them, hands each integrated
scan to the pose-graph back end when it is on (`omnitof.slam.backend`), and turns the result
into a map and a trajectory with a pose for every scan: the best particle's, or with the back
end the optimised graph's, whose poses also build the map.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from omnitof import _core
from omnitof.errors import InputError, ResourceError
from omnitof.slam.anchor import moved, moved_back, run_offset
from omnitof.slam.backend import FrontEnd2D, PoseGraphBackend
from omnitof.slam.limits import MemoryWatch, check_limits, usable_cores, within_cores
from omnitof.slam.config import SlamConfig
from omnitof.slam.final_match import final_match, grid_along
from omnitof.slam.footprint import clear_footprint
from omnitof.slam.moving import drop_moving
from omnitof.slam.scan_odometry import with_scan_odometry
from omnitof.slam.thinning import thin_dense_scans
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
    map: the best particle's occupancy grid, or with the back end the grid of every integrated
        scan at its optimised pose.
    stats: counts and timings of the run.
    graph: with the back end, its nodes' optimised poses (K, 3) (the integrated scans, in
        order), the accepted and rejected loop closures as (K_c, 2) node index pairs, and the
        nodes where the odometry check relocalised the robot onto an older map ("relocalised").
    """

    trajectory: Trajectory
    odometry: Trajectory
    integrated: np.ndarray
    map: OccupancyMap
    stats: dict = field(default_factory=dict)
    graph: dict | None = None


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


# The filter section's fields this driver uses itself (which scans to integrate, the poses of the
# others); the core's filters (2D and 3D) refuse them as unknown.
DRIVER_FILTER_FIELDS = frozenset({
    "linear_update", "angular_update_deg", "match_between", "final_match_passes", "moving_lookback", "moving_margin",
})
# The map section's fields the driver applies itself: before the filter (omnitof.slam.thinning)
# and to the map written at the end (omnitof.slam.footprint).
DRIVER_MAP_FIELDS = frozenset({"max_beams", "thin_beams", "footprint_radius"})


def core_sections(cfg: SlamConfig) -> dict:
    """The configuration's sections as the core's filter takes them: every section but the
    back end's, the 3D filter's and the scan extraction's, less the fields this driver uses itself (which scans to
    integrate, the poses of the others, the thinning of dense scans)."""
    return cfg.model_dump(
        exclude={"filter": set(DRIVER_FILTER_FIELDS), "map": set(DRIVER_MAP_FIELDS), "backend": True,
                 "filter3d": True, "scan": True}
    )


def _make_filter(scans: ScanSequence, cfg: SlamConfig) -> "_core.ParticleFilter":
    """The core's filter for a configuration and a sensor. The core takes every section whole,
    as one keyword each, and derives what it needs (radians, ranges capped by the sensor's,
    threads); only the scan selection (`select_scans`) is done here and kept out of it."""
    return _core.ParticleFilter(
        **core_sections(cfg), angles=scans.scan_angles(0), sensor_pose=scans.sensor_pose,
        scan_max_range=scans.max_range,
    )


class _Between:
    """Poses of the scans between integrated ones, each from one local match in the best
    particle's map, started where the previous scan's pose and the odometry put it; where too
    few of its end points find the map (fewer than `scan_matcher.min_matched`), the odometry's
    prediction stands. Each pose is kept relative to the front end's pose of the integrated scan
    before it, so that it follows that scan's final (or optimised) pose."""

    def __init__(self, scans: ScanSequence, cfg: SlamConfig):
        self.scans = scans
        self.min_matched = cfg.scan_matcher.min_matched
        self.relative = np.zeros((len(scans), 3))
        self.next = 0  # first scan not yet posed
        self.matched = 0
        self.by_odometry = 0

    def match_up_to(self, pf: "_core.ParticleFilter", stop: int) -> None:
        """Pose the scans from the last integrated one up to (not including) `stop`, in the map
        as it is now (it holds every scan integrated before them); one call into the core."""
        first = self.next
        self.next = stop + 1
        if first >= stop or pf.best_pose() is None:  # before the first scan: no map yet
            return
        angles = self.scans.angles[first:stop] if self.scans.per_scan_geometry else None
        found = pf.match_scans(self.scans.odometry[first - 1:stop], self.scans.ranges[first:stop],
                               self.min_matched, angles=angles)
        poses, matched = found
        self.relative[first:stop] = poses
        self.matched += int(matched.sum())
        self.by_odometry += int((~matched).sum())

    def trajectory(self, integrated: np.ndarray, corrected: np.ndarray) -> np.ndarray:
        """Every scan's pose: integrated scans at `corrected`, the others after their anchor."""
        last = np.searchsorted(integrated, np.arange(len(self.scans)), side="right") - 1
        poses = compose(corrected[last], self.relative)
        poses[integrated] = corrected
        return poses


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
    scans processed since its last call (for a progress bar).

    Raises:
        InputError, ResourceError, ConfigError: scans that cannot make a map, a run that
            cannot fit (omnitof.slam.limits.check_limits, before the filter starts), memory
            that ran out all the same.
    """
    cfg = within_cores(cfg)
    scans, _ = thin_dense_scans(scans, cfg)  # slam_run has thinned them already, and says so in its summary
    estimated = None
    if not scans.odometry_known:  # slam_run has estimated it already, and says so in its summary
        check_limits(scans, cfg)  # a log with nothing to map says so before the estimate's work
        scans, estimated = with_scan_odometry(scans, cfg)
    check_limits(scans, cfg)
    offset = run_offset(scans.odometry, cfg.map.resolution)  # odometry far out (slam.anchor)
    try:
        result = in_odometry_frame(_run(moved(scans, offset), cfg, progress), offset, scans)
    except MemoryError as err:  # the core's allocations fail as MemoryError, never as an abort
        raise ResourceError(
            f"out of memory during SLAM ({err or 'no detail'}) with filter.particles "
            f"{cfg.filter.particles} and map.resolution {cfg.map.resolution:g} m: choose fewer "
            "particles or a coarser resolution"
        ) from None
    if estimated is not None:
        result.stats["scan_odometry"] = estimated.to_dict()
    if not result.map.known.any():
        raise InputError(
            "no scan left a mark in the map (no beam echoed within map.max_range "
            f"{cfg.map.max_range:g} m, and map.clear_no_echo is off): there is nothing to map",
            scans.source or None,
        )
    result.map = clear_footprint(result.map, result.trajectory.poses, cfg.map.footprint_radius, cfg.map.l_min)
    return result


def in_odometry_frame(result: SlamResult, offset: np.ndarray, scans: ScanSequence) -> SlamResult:
    """A result of the run moved by -offset (omnitof.slam.anchor) in the odometry's own frame."""
    if not np.any(offset):
        return result
    result.trajectory = Trajectory(result.trajectory.timestamps, moved_back(result.trajectory.poses, offset))
    result.odometry = Trajectory(scans.timestamps, scans.odometry)
    x0, y0 = result.map.origin
    result.map.origin = (x0 + float(offset[0]), y0 + float(offset[1]))
    if result.graph is not None:
        result.graph["nodes"] = moved_back(result.graph["nodes"], offset)
    return result


def _run(scans: ScanSequence, cfg: SlamConfig, progress: Callable[[int], None] | None) -> SlamResult:
    start = time.perf_counter()
    moving = None
    if cfg.filter.moving_lookback > 0:
        scans, moving = drop_moving(scans, cfg.filter.moving_lookback, cfg.filter.moving_margin)
    integrated = select_scans(
        scans.odometry, cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg)
    )
    pf = _make_filter(scans, cfg)
    backend = None
    if cfg.backend.enabled:
        threads = cfg.filter.threads or usable_cores()
        backend = PoseGraphBackend(cfg.backend, cfg.map, cfg.likelihood_field.sigma, scans, threads)
        front = FrontEnd2D(pf, scans, cfg.map)
    prev = scans.odometry[integrated[0]]
    done = 0
    corrected_scans = []
    memory = MemoryWatch("SLAM", f"choose fewer than filter.particles {cfg.filter.particles} or a coarser "
                                 f"map.resolution than {cfg.map.resolution:g} m")
    between = _Between(scans, cfg) if cfg.filter.match_between else None
    for step, k in enumerate(integrated, start=1):
        if between is not None:
            between.match_up_to(pf, int(k))
        cur = scans.odometry[k]
        own = scans.scan_angles(k) if scans.per_scan_geometry else None  # else the filter's
        check_corrected = bool(pf.step(prev, cur, scans.scan_ranges(k), int(k), angles=own)[2])
        if check_corrected:
            corrected_scans.append(int(k))
        prev = cur
        if backend is not None:
            backend.add_node(int(k), front, check_corrected)
        memory.check(step, len(integrated))
        if progress is not None:
            progress(int(k) + 1 - done)
            done = int(k) + 1
    if between is not None:
        between.match_up_to(pf, len(scans))
    if progress is not None and done < len(scans):
        progress(len(scans) - done)
    unique_tiles, tile_refs = pf.tile_counts()
    graph = grid = None
    if backend is None:
        scan_idx, corrected = pf.best_trajectory()
        assert np.array_equal(scan_idx, integrated)
        log_odds, ix0, iy0 = pf.best_map()
    else:
        corrected = backend.finish(front)
        grid = backend.build_grid()
        log_odds, ix0, iy0 = grid.to_dense()
        graph = backend.graph(corrected)
    if between is None:
        poses = fill_trajectory(scans.odometry, integrated, corrected)
    else:
        poses = between.trajectory(integrated, corrected)
    stood = None
    final_start = time.perf_counter()
    if cfg.filter.final_match_passes:
        if grid is None:  # the filter's own map: the best particle's, along its trajectory
            grid = grid_along(scans, integrated, corrected, cfg.map)
        poses, grid, stood = final_match(grid, scans, integrated, poses, cfg)
        log_odds, ix0, iy0 = grid.to_dense()
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
    if moving is not None:
        stats["moving_readings_dropped"] = moving.total
        stats["moving_scans_kept_whole"] = moving.scans_kept_whole
    if between is not None:
        stats["between_scans_matched"] = between.matched
        stats["between_scans_by_odometry"] = between.by_odometry
    if stood is not None:
        stats["final_match_stood"] = stood
        stats["final_match_seconds"] = time.perf_counter() - final_start
    if backend is not None:
        stats["backend"] = backend.stats()
        stats["loop_closures"] = backend.closure_table()
        stats["check_corrections"] = backend.correction_table()
    return SlamResult(
        trajectory=Trajectory(scans.timestamps, poses),
        odometry=Trajectory(scans.timestamps, scans.odometry),
        integrated=integrated,
        map=dense_to_map(log_odds, ix0, iy0, cfg.map.resolution),
        stats=stats,
        graph=graph,
    )

