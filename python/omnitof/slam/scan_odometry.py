"""Odometry from the scans themselves, for inputs that have none.

Some logs carry no odometry: a laser carried by hand (Cartographer's backpack bags), a bag of a
lidar alone, a robot whose wheel encoders were not recorded; and some odometry is too broken to
use (`omnitof slam --ignore-odometry`). The filter needs a motion between scans to predict from
and to decide when to integrate. Here each scan is matched by the filter's own local matcher
(hill climbing, then Gauss-Newton, on the likelihood field: rust/src/scan_match.rs) against a
local map of the scans of the last `LOCAL_PATH` metres of path at their estimated poses, within
the map's range. The climb starts both where the motion of the scan before would carry the
robot (the same step again) and where that scan was (the robot stopped), and the better match
is kept; where the match finds too little of the map, it also starts at every 10° of heading
around, and after a gap in the log (`gap_threshold`) also along arcs of every turn as long as
the robot's motion before the gap would have taken it (taken where clearly better). Where fewer than
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
# A scan taken this many typical intervals after the one before (a gap in the log), or whose
# match finds too little of the map, is also matched from these headings about the pose before
# and, after a gap, about where the robot's motion before it may have carried it. Where the
# log's scans come irregularly, an interval up to GAP_SLACK times the GAP_QUANTILE of its
# intervals is its rhythm, not a gap, up to GAP_MIN_S: Intel's run from -0.6 to 1.5 s around
# 0.1 s (97 % within 1.03 s), and 3686 of them would otherwise count as gaps (150 s of wide
# searches where 40 s give a better estimate: BENCHMARKS.md, "ToF bags without odometry ...").
# A lidar at 40 Hz with regular stamps keeps three of its intervals: a turn of 30° in a
# dropout of 0.3 s is beyond the local climb.
GAP = 3.0
GAP_QUANTILE = 0.97
GAP_SLACK = 1.5
GAP_MIN_S = 1.0
# After a gap the motion of the scan before is carried on for at most this many intervals.
MAX_CARRIED_STEPS = 100
# A match started where that motion may have carried the robot replaces the best from the pose
# before only if it scores this much more: on the benchmark logs the two reach the same pose
# (their scores differ in the third decimal, on scores of 0.1-1.9), and a choice between them
# would only make the estimate differ by chance; where the robot went on round a corner the
# gain is tenths (0.76 in tests/test_scan_odometry.py's gap at a corner).
ARC_MARGIN = 0.01
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
                 gauss_newton=sm.gauss_newton, threads=cfg.filter.threads or None)
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
    gap_after = gap_threshold(intervals)
    matched = unmatched = gaps = 0
    added = 1  # keyframes, the first scan's included
    reported = 0  # scans passed to `progress`
    for k in range(1, n):  # each scan's start is the scan before it's result
        predicted = compose(poses[k - 1], last_step)
        angles, ranges = scans.scan_angles(k), np.ascontiguousarray(scans.scan_ranges(k))
        best, _ = _best_match(grid, (predicted, poses[k - 1]), angles, ranges, match, steps)
        share = _share(grid, best, angles, ranges, match, lf)
        interval = float(scans.timestamps[k] - scans.timestamps[k - 1])
        gap = interval > gap_after
        gaps += gap
        if gap or share < sm.min_matched:
            # A gap in the log (ACES turns 70° in one of 3 s) or a lost match: the local climb
            # cannot reach a turn of tens of degrees, so start it at every heading around. After
            # a gap the robot also went on: a corner taken at 1 m/s in 1.6 s leaves it 0.65 m
            # from where it was, beyond the climb's reach from there.
            turned = [poses[k - 1] + [0.0, 0.0, a] for a in WIDE_HEADINGS]
            wide, score = _best_match(grid, [best, *turned], angles, ranges, match, steps)
            arcs = _arcs(poses[k - 1], last_step, interval / typical_interval) if gap else []
            if arcs:
                carried, carried_score = _best_match(grid, arcs, angles, ranges, match, steps)
                if carried_score > score + ARC_MARGIN:
                    wide = carried
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


def gap_threshold(intervals: np.ndarray) -> float:
    """The interval (s) beyond which a scan follows a gap in the log, from the log's positive
    intervals between scans: GAP typical ones, or more where its rhythm is irregular (GAP_SLACK
    times the GAP_QUANTILE of them, at most GAP_MIN_S)."""
    if len(intervals) == 0:
        return math.inf
    rhythm = min(GAP_MIN_S, GAP_SLACK * float(np.quantile(intervals, GAP_QUANTILE)))
    return max(GAP * float(np.median(intervals)), rhythm)


def _arcs(pose: np.ndarray, step: np.ndarray, steps: float) -> list[np.ndarray]:
    """Where a robot at `pose` that moved by `step` per scan may be `steps` scans later: its path
    that long, or half that long (it slowed down), bent by any of WIDE_HEADINGS' turns, with
    the heading the turn gives."""
    length = math.hypot(step[0], step[1]) * min(steps, MAX_CARRIED_STEPS)
    if length == 0.0:
        return []
    ends = []
    for d in (length, 0.5 * length):
        for turn in WIDE_HEADINGS:
            chord = d if turn == 0.0 else d * math.sin(turn / 2) / (turn / 2)
            ends.append(compose(pose, np.array([chord * math.cos(turn / 2), chord * math.sin(turn / 2), turn])))
    return ends


def _best_match(grid: _core.OccupancyGrid, starts, angles: np.ndarray, ranges: np.ndarray, match: dict,
                steps: dict) -> tuple[np.ndarray, float]:
    """The pose and score of the best-scoring local match among those started at each of
    `starts` (at least one; the first of equal scores, whatever the thread count)."""
    found, score = grid.match_best(np.asarray(starts, dtype=np.float64).reshape(-1, 3), angles, ranges,
                                   **match, **steps)
    return np.asarray(found), score


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
