"""Odometry from the scans themselves, for inputs that have none.

Some logs carry no odometry: a laser carried by hand (Cartographer's backpack bags), a bag of a
lidar alone, a robot whose wheel encoders were not recorded; and some odometry is too broken to
use (`omnitof slam --ignore-odometry`). The filter needs a motion between scans to predict from
and to decide when to integrate. Here each scan is matched by the filter's own local matcher
(hill climbing, then Gauss-Newton, on the likelihood field: rust/src/scan_match.rs) against a
local map of the scans of the last `LOCAL_PATH` metres of path at their estimated poses, within
the map's range. The climb starts both where the motion of the scan before would carry the
robot (the same step again) and where that scan was (the robot stopped), and the better match
is kept; after a gap in the log (of a second or more), or where the match finds too little of
the map, it also starts at every 10° of heading around. Where fewer than
`scan_matcher.min_matched` of its end points find the map all the same, the step before is
repeated and the scan joins the map at that pose. The poses so found are the odometry the
filter then runs on: good over a few metres,
drifting over long distances as wheels do; closing loops stays the filter's and the back end's
work.

Written here: the matcher is the core's; this module only chooses the map each scan meets, as
Hector SLAM and Cartographer's local SLAM do without odometry. The loop over scans is in Python
because each scan's match depends on the one before; the work of each is a few core calls.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from omnitof import _core
from omnitof.geometry import compose, relative, wrap_angle
from omnitof.slam.config import SlamConfig
from omnitof.types import ScanSequence

# A scan joins the local map after the robot moved this far (m) or turned this much (rad)
# since the last one that did: the map then holds walls seen from poses 10 cm apart, which
# is what the filter's own map holds at its default linear_update of 0.5 m and more.
KEYFRAME_DISTANCE = 0.1
KEYFRAME_ANGLE = math.radians(5.0)
# The local map holds the keyframes of this much path (m) behind the newest. Long enough that
# a corridor's far walls stay in it, short enough that the drift within it is centimetres.
LOCAL_PATH = 10.0
# The local map is rebuilt from its keyframes after this much path (m), dropping the old ones.
REBUILD_PATH = 2.0
# A step longer than this (m per scan) or turning more (rad per scan) is not predicted again:
# the step of a scan that matched badly would otherwise carry the next ones away.
MAX_STEP = 1.0
MAX_TURN = math.radians(45.0)
# A scan taken this many typical intervals after the one before, and at least GAP_MIN_S later
# (a gap in the log), or whose match finds too little of the map, is also matched from these
# headings about the pose before. The floor is for logs whose scans come irregularly: Intel's
# intervals run from -0.6 to 1.5 s around 0.1 s, and 3686 of its scans would otherwise count as
# gaps (150 s of wide searches where 40 s give a better estimate: BENCHMARKS.md, "ToF bags
# without odometry ..."). Below a second the local climb, or the search after a failed match,
# copes with what a robot turns.
GAP = 3.0
GAP_MIN_S = 1.0
WIDE_HEADINGS = np.radians(np.arange(-180.0, 180.0, 10.0))


@dataclass(frozen=True)
class ScanOdometry:
    """What `estimate_odometry` did."""

    matched: int  # scans posed by their match
    unmatched: int  # scans whose match found too little of the map: the prediction (the step before) stands
    keyframes: int  # scans that went into the local map
    gaps: int = 0  # scans after a gap in the log, matched from every heading too

    def to_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


def with_scan_odometry(scans: ScanSequence, cfg: SlamConfig, *,
                       progress: Callable[[int], None] | None = None) -> tuple[ScanSequence, ScanOdometry]:
    """`scans` with its odometry replaced by `estimate_odometry`'s (odometry_known, and the
    rule saying so)."""
    poses, stats = estimate_odometry(scans, cfg, progress=progress)
    rule = (f"estimated from the scans ({stats.matched} matched, {stats.unmatched} by the step before): "
            + (scans.odometry_rule or "the input had none"))
    return dataclasses.replace(scans, odometry=poses, odometry_known=True, odometry_rule=rule), stats


def estimate_odometry(scans: ScanSequence, cfg: SlamConfig, *,
                      progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, ScanOdometry]:
    """(N, 3) poses of every scan, each matched against the local map of the scans before it
    (see the module's docstring), and what was done. The first pose is where the input's
    odometry puts it: the origin where it has none, its own first pose where `--ignore-odometry`
    set it aside (so that the two share a frame). `progress(n)` is called with the number of
    scans done since its last call."""
    n = len(scans)
    poses = np.zeros((n, 3))  # from the origin; moved to the input's first pose at the end
    if n == 0:
        return poses, ScanOdometry(0, 0, 0)
    m, lf, sm = cfg.map, cfg.likelihood_field, cfg.scan_matcher
    # The map's range, not the sensor model's shorter one (15 m in the laser preset): without
    # odometry only the walls at a corridor's far end say how far along it the robot moved
    # (ACES: 0.44 m mean relations error at 15 m, 0.09 m at 20 m, BENCHMARKS.md).
    max_range = min(m.max_range, scans.max_range)
    match = dict(sensor_pose=scans.sensor_pose, sigma=lf.sigma, window=lf.window_cells, max_range=max_range,
                 occupied_threshold=m.occupied_threshold)
    steps = dict(step_xy=sm.step_xy, step_theta=math.radians(sm.step_deg), refinements=sm.refinements,
                 gauss_newton=sm.gauss_newton)
    path = np.zeros(n)  # estimated path length up to each scan
    keyframes = [0]
    grid = _local_map(scans, poses, keyframes, cfg)
    rebuilt_at = 0.0
    # The motion of the scan before, in the robot's frame: per scan, not per second, since real
    # logs' stamps jitter (Intel's step back 631 times) and a step over a stamp 1 ms apart
    # would read as a velocity that throws the next prediction metres away.
    last_step = np.zeros(3)
    intervals = np.diff(scans.timestamps)
    intervals = intervals[intervals > 0]
    typical_interval = float(np.median(intervals)) if len(intervals) else math.inf
    matched = unmatched = gaps = 0
    added = 1  # keyframes, the first scan's included
    reported = 0  # scans passed to `progress`
    for k in range(1, n):  # each scan's start is the scan before it's result
        predicted = compose(poses[k - 1], last_step)
        angles, ranges = scans.scan_angles(k), np.ascontiguousarray(scans.scan_ranges(k))
        best = _best_match(grid, (predicted, poses[k - 1]), angles, ranges, match, steps)
        share = _share(grid, best, angles, ranges, match, lf)
        gap = float(scans.timestamps[k] - scans.timestamps[k - 1]) > max(GAP * typical_interval, GAP_MIN_S)
        gaps += gap
        if gap or share < sm.min_matched:
            # A gap in the log (ACES turns 70° in one of 3 s) or a lost match: the local climb
            # cannot reach a turn of tens of degrees, so start it at every heading around.
            turned = [poses[k - 1] + [0.0, 0.0, a] for a in WIDE_HEADINGS]
            wide = _best_match(grid, [best, *turned], angles, ranges, match, steps)
            if wide is not best:
                best, share = wide, _share(grid, wide, angles, ranges, match, lf)
        lost = share < sm.min_matched
        poses[k] = predicted if lost else best
        unmatched += lost
        matched += not lost
        step = relative(poses[k - 1], poses[k])
        path[k] = path[k - 1] + math.hypot(step[0], step[1])
        believed = math.hypot(step[0], step[1]) <= MAX_STEP and abs(step[2]) <= MAX_TURN
        last_step = step if believed else np.zeros(3)
        last = poses[keyframes[-1]]
        # A scan whose match failed joins the map too: where the map holds too little (a blind
        # or sparse first scan, a lidar spinning up) the estimate would otherwise stand still
        # for the whole log, no scan ever moving far enough to join it.
        if (lost or math.hypot(*(poses[k, :2] - last[:2])) >= KEYFRAME_DISTANCE
                or abs(wrap_angle(poses[k, 2] - last[2])) >= KEYFRAME_ANGLE):
            keyframes.append(k)
            added += 1
            if path[k] - rebuilt_at >= REBUILD_PATH:
                keyframes = [j for j in keyframes if path[k] - path[j] <= LOCAL_PATH]
                grid = _local_map(scans, poses, keyframes, cfg)
                rebuilt_at = path[k]
            else:
                _integrate(grid, scans, poses, k, cfg)
        if progress is not None and k % 100 == 0:
            progress(k + 1 - reported)
            reported = k + 1
    if progress is not None and reported < n:
        progress(n - reported)
    # Matched near the origin, where the grid's cells are small numbers (a georeferenced start
    # millions of metres out is omnitof.slam.anchor's case), then moved there.
    return compose(scans.odometry[0], poses), ScanOdometry(matched, unmatched, added, gaps)


def _best_match(grid: _core.OccupancyGrid, starts, angles: np.ndarray, ranges: np.ndarray, match: dict,
                steps: dict) -> np.ndarray:
    """The pose of the best-scoring local match among those started at each of `starts` (the
    first of equal scores)."""
    best, best_score = None, -math.inf
    for start in starts:
        found, score = grid.match_scan(np.asarray(start, dtype=np.float64), angles, ranges, **match, **steps)
        if best is None or score > best_score:
            best, best_score = np.asarray(found), score
    return best


def _share(grid: _core.OccupancyGrid, pose: np.ndarray, angles: np.ndarray, ranges: np.ndarray, match: dict,
           lf) -> float:
    """The share of the scan's end points at `pose` that lie near an obstacle of `grid`."""
    _, share = grid.match_each(pose[None, :], ranges[None, :], angles, z_hit=lf.z_hit, z_rand=lf.z_rand,
                               gauss_newton=0, threads=1, **match)
    return float(share[0])


def _local_map(scans: ScanSequence, poses: np.ndarray, keyframes: list[int], cfg: SlamConfig) -> _core.OccupancyGrid:
    m = cfg.map
    grid = _core.OccupancyGrid(m.resolution, m.l_occ, m.l_free, m.l_min, m.l_max)
    for k in keyframes:
        _integrate(grid, scans, poses, k, cfg)
    return grid


def _integrate(grid: _core.OccupancyGrid, scans: ScanSequence, poses: np.ndarray, k: int, cfg: SlamConfig) -> None:
    grid.integrate(poses[k], scans.scan_angles(k), np.ascontiguousarray(scans.scan_ranges(k)),
                   min(cfg.map.max_range, scans.max_range), clear_no_echo=cfg.map.clear_no_echo,
                   sensor_pose=scans.sensor_pose)
