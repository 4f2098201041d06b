"""Readings of things that move: dropped before the filter sees them.

A reading whose end point lies in space that an earlier scan saw through (its beam at that
bearing reached clearly farther) hit something that was not there before: a person, most
often, walking beside the robot or across its way. The filter takes every reading for a wall,
lays people walking with the robot onto the map, and drifts along the corridor with them (on
the simulated wide loop with people beside the robot, 0.42 m mean error against 0.13 m without
them; BENCHMARKS.md, "Readings of things that move"). The earlier scan is the one a
`lookback` of odometry path behind (2 m in the measurements): near enough that the odometry
between the two is good to a few centimetres, far enough that a person keeping pace with the
robot did not hide the spot from it (at 1 m, it mostly did). Each reading of scan k is moved
into that scan's sensor frame by the odometry, and its range there compared with that scan's
readings at the two beams around its bearing: where both reached farther by `margin`, within
the sensor's range, the reading is dropped (it reads as no echo), if it lies in a run of at
least `min_run` such neighbouring readings. Where more than `max_share` of a scan would be
dropped, none is: the odometry between the two scans is then more likely wrong (a wheel glitch)
than the scene so full of people. The moving objects' readings are then neither matched nor
mapped; the walls they hid stay unseen for those scans.

Written here: no library of the field offers free-space differencing of planar scans (people
trackers, e.g. ROS's leg_detector, classify scan segments by shape instead).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from omnitof.geometry import compose, relative
from omnitof.types import ScanSequence


@dataclass(frozen=True)
class MovingReadings:
    """What `drop_moving` did: the readings dropped, per scan, and the scans it left alone
    because too much of them would have gone."""

    dropped: np.ndarray  # (N,) int
    scans_kept_whole: int

    @property
    def total(self) -> int:
        return int(self.dropped.sum())


def _runs_of_at_least(flags: np.ndarray, length: int) -> np.ndarray:
    """`flags` (B,) with every run of consecutive trues shorter than `length` cleared."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(np.int8), [0]])))
    starts, stops = edges[::2], edges[1::2]
    long_enough = stops - starts >= length
    # +1 where a kept run starts, -1 where it stops: the running sum is 1 inside kept runs.
    marks = np.zeros(len(flags) + 1, dtype=np.int32)
    marks[starts[long_enough]] += 1
    marks[stops[long_enough]] -= 1
    return np.cumsum(marks[:-1]) > 0


def moving_mask(scans: ScanSequence, lookback: float, margin: float, max_share: float = 0.3,
                min_run: int = 3) -> tuple[np.ndarray, int]:
    """(N, B) bool: the readings of each scan in space the scan `lookback` metres of odometry
    path before it saw through by more than `margin` metres, in runs of at least `min_run`
    neighbouring beams (a person at a few metres spans many; the edge of a corner that comes
    into view, which the earlier scan saw past, one or two); and how many scans were left
    whole (more than `max_share` of their readings would have gone)."""
    n = len(scans)
    mask = np.zeros(scans.ranges.shape, dtype=bool)
    if n < 2:
        return mask, 0
    steps = np.hypot(*np.diff(scans.odometry[:, :2], axis=0).T)
    path = np.concatenate([[0.0], np.cumsum(steps)])
    # The latest scan at least `lookback` behind each scan along the path (-1: none yet).
    ref = np.searchsorted(path, path - lookback, side="right") - 1
    world_T_sensor = compose(scans.odometry, scans.sensor_pose)
    kept_whole = 0
    for k in np.flatnonzero(ref >= 0):  # per scan; its beams at once
        j = int(ref[k])
        r_k, a_k = scans.scan_ranges(k).astype(np.float64), scans.scan_angles(k)
        r_j, a_j = scans.scan_ranges(j).astype(np.float64), scans.scan_angles(j)
        bearing_known = np.isfinite(a_j)  # scan_angles gives a scan's own beams; guard all the same
        r_j, a_j = r_j[bearing_known], a_j[bearing_known]
        reading = np.isfinite(r_k) & (r_k > 0)
        if not reading.any() or len(a_j) < 2:
            continue
        j_T_k = relative(world_T_sensor[j], world_T_sensor[k])
        c, s = np.cos(j_T_k[2] + a_k), np.sin(j_T_k[2] + a_k)
        r_k = np.where(reading, r_k, 0.0)  # no echo stays out (and inf·0 makes no NaN)
        x, y = j_T_k[0] + r_k * c, j_T_k[1] + r_k * s
        seen_at, bearing = np.hypot(x, y), np.arctan2(y, x)
        order = np.argsort(a_j)
        a_sorted, r_sorted = a_j[order], np.where(np.isfinite(r_j[order]), r_j[order], np.inf)
        right = np.searchsorted(a_sorted, bearing)
        inside = (right > 0) & (right < len(a_sorted))  # within scan j's field of view
        right = np.clip(right, 1, len(a_sorted) - 1)
        beyond = np.minimum(r_sorted[right - 1], r_sorted[right])
        # No echo from scan j says free space only out to the sensor's range: a point beyond
        # that (a far wall seen at a slant) was never seen through.
        moving = reading & inside & (beyond > seen_at + margin) & (seen_at + margin < scans.max_range)
        moving = _runs_of_at_least(moving, min_run)
        if moving.sum() > max_share * reading.sum():
            kept_whole += 1
            continue
        mask[k, : len(moving)] = moving
    return mask, kept_whole


def drop_moving(scans: ScanSequence, lookback: float, margin: float) -> tuple[ScanSequence, MovingReadings]:
    """`scans` with the readings of moving things (`moving_mask`) turned into no echo."""
    mask, kept_whole = moving_mask(scans, lookback, margin)
    if not mask.any():
        return scans, MovingReadings(mask.sum(axis=1), kept_whole)
    ranges = scans.ranges.copy()
    ranges[mask] = np.inf
    return dataclasses.replace(scans, ranges=ranges), MovingReadings(mask.sum(axis=1), kept_whole)
