"""The delay between taking a scan and stamping it, estimated from the data, and odometry re-timed
for it.

A laser stamps a scan when the reading arrives, which can be a good part of a sweep after the
sweep: a SICK LMS on a serial line needs about a tenth of a second to send 361 ranges. The
odometry pose logged with the scan is then where the robot was *after* it took the scan, wrong
by the turn made in between. In the Freiburg 079 log the odometry taken 0.12 s before each
scan's stamp matches the benchmark's reference relations about twice as well in heading (mean
error 1.1° instead of 2.3° over the short relations); the scan matcher corrects the integrated
scans, but the poses between them follow the odometry.

The estimate needs no reference: scan-match each scan against the one before it while the robot
turns, and find the delay at which the odometry's turn between the two (re-timed) agrees best
with the matched one. A delay changes that turn only where the turn rate changes, so the pairs
where the robot starts or stops turning carry the information.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from omnitof.geometry import interpolate_poses, relative, wrap_angle
from omnitof.types import ScanSequence, Trajectory

# The most a laser's own delay can be (s): a sweep and its transfer. Beyond it the laser's and
# the odometry's clocks disagree (`estimate_scan_delay` then searches wider).
LASER_DELAY = 0.3
# In the wider search, a second minimum this far (s) from the best and within this ratio of its
# heading error makes the estimate ambiguous.
AMBIGUOUS_APART = 0.5
AMBIGUOUS_RATIO = 2.0


@dataclass
class ScanDelay:
    """A scan delay estimate.

    Attributes:
        delay: the estimated delay (s): each scan was taken this long before its timestamp.
        delays: (K,) the delays tried (s).
        heading_error: (K,) mean absolute difference (rad) between the matched turn and the
            re-timed odometry's turn over the pairs, per delay tried.
        pairs: how many scan pairs matched well enough to count.
    """

    delay: float
    delays: np.ndarray
    heading_error: np.ndarray
    pairs: int


def retime_odometry(scans: ScanSequence, delay: float) -> ScanSequence:
    """A copy of `scans` whose odometry pose of each scan is the odometry at its timestamp minus
    `delay`, interpolated along the scans' own odometry poses (linear in x and y, along the
    shorter arc in theta) and held at the first and last pose beyond them.

    Raises:
        ValueError: if the timestamps do not increase everywhere (the Intel log's step back; a
            stamp shared by two scans with different poses is as ambiguous): time then cannot
            tell where the robot was.
    """
    if delay == 0.0 or len(scans) == 0:
        return scans
    if np.any(np.diff(scans.timestamps) <= 0):
        raise ValueError(
            f"{scans.source or 'scans'}: timestamps do not increase everywhere, so the odometry "
            "cannot be re-timed"
        )
    t = scans.timestamps
    query = np.clip(t - delay, t[0], t[-1])
    poses = interpolate_poses(Trajectory(t, scans.odometry), query)
    return dataclasses.replace(scans, odometry=poses)


def estimate_scan_delay(
    scans: ScanSequence,
    *,
    max_delay: float = LASER_DELAY,
    widest: float = 10.0,
    step: float = 0.01,
    min_turn_deg: float = 3.0,
    max_pairs: int = 600,
    max_range: float = 15.0,
) -> ScanDelay:
    """Estimate the scan delay (see the module notes) over the delays −max_delay..max_delay, or,
    where the best of those lies at either end, over −widest..widest: the laser's and the
    odometry's clocks then disagree (a bag whose two drivers stamp by different clocks), by more
    than a laser's own delay.

    Scan pairs: consecutive scans between which the odometry turned at least `min_turn_deg`,
    up to `max_pairs` spread evenly over the log. Each later scan is matched (omnitof._core,
    hill climbing and Gauss-Newton on a likelihood field) against a 5 cm grid of the earlier one
    alone, from the odometry's prediction; pairs that match poorly (mean end-point
    log-likelihood below 0.5) are left out. The delay with the smallest mean heading
    difference is refined by a parabola through it and its neighbours.

    Raises:
        ValueError: if the timestamps do not increase everywhere, no pair of scans turned,
            fewer than 20 pairs match, or (in the wider search) the best delay lies at ±widest or
            another one half a second or more away explains the turns almost as well.
    """
    from omnitof import _core

    if np.any(np.diff(scans.timestamps) <= 0):
        raise ValueError(
            f"{scans.source or 'scans'}: timestamps do not increase everywhere, so no scan delay "
            "can be estimated"
        )
    turn = np.abs(wrap_angle(np.diff(scans.odometry[:, 2])))
    candidates = np.flatnonzero((turn >= np.radians(min_turn_deg)) & (np.diff(scans.timestamps) > 0))
    if len(candidates) > max_pairs:
        candidates = candidates[np.linspace(0, len(candidates) - 1, max_pairs).round().astype(int)]
    matched_turn, used = [], []
    for k in candidates:
        grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
        grid.integrate(np.zeros(3), scans.scan_angles(k), scans.scan_ranges(k), max_range, False, scans.sensor_pose)
        predicted = relative(scans.odometry[k], scans.odometry[k + 1])
        pose, score = grid.match_scan(
            predicted, scans.scan_angles(k + 1), scans.scan_ranges(k + 1), sensor_pose=scans.sensor_pose,
            max_range=max_range,
        )
        if score >= 0.5:
            matched_turn.append(pose[2])
            used.append(k)
    if not len(candidates):  # a log of a few scans, or one that never turns
        raise ValueError(
            f"{scans.source or 'scans'}: no scan pair taken while turning (by {min_turn_deg:g}° or more) to "
            "estimate the scan delay from"
        )
    if len(used) < 20:
        raise ValueError(
            f"{scans.source or 'scans'}: only {len(used)} of the {len(candidates)} scan pairs taken while turning "
            "match well; too few (20 needed) to estimate a scan delay"
        )
    first = np.asarray(used)
    matched_turn = np.asarray(matched_turn)
    trajectory = Trajectory(scans.timestamps, scans.odometry)
    t = scans.timestamps

    def heading_errors(delays: np.ndarray) -> np.ndarray:
        """Mean |matched turn − odometry turn| per delay, every (delay, pair) at once."""
        shifted = delays[:, None]
        a = interpolate_poses(trajectory, np.clip(t[first] - shifted, t[0], t[-1]).ravel())
        b = interpolate_poses(trajectory, np.clip(t[first + 1] - shifted, t[0], t[-1]).ravel())
        turns = relative(a, b)[:, 2].reshape(len(delays), len(first))
        return np.mean(np.abs(wrap_angle(matched_turn - turns)), axis=1)

    delays = np.arange(-max_delay, max_delay + step / 2, step)
    errors = heading_errors(delays)
    best = int(np.argmin(errors))
    if best in (0, len(delays) - 1) and widest > max_delay:
        delays = np.arange(-widest, widest + step / 2, step)
        errors = heading_errors(delays)
        best = int(np.argmin(errors))
        # A robot that turns to a rhythm agrees with itself a period later: two near-equal
        # minima are no estimate.
        apart = np.abs(delays - delays[best]) > AMBIGUOUS_APART
        if apart.any() and errors[apart].min() < AMBIGUOUS_RATIO * errors[best]:
            other = float(delays[apart][np.argmin(errors[apart])])
            raise ValueError(
                f"{scans.source or 'scans'}: the odometry's turns agree with the scans' as well at a delay of "
                f"{delays[best]:+.2f} s as at {other:+.2f} s (the robot turns to a rhythm): no delay can be told "
                "(give --scan-delay SECONDS)"
            )
        if best in (0, len(delays) - 1):
            raise ValueError(
                f"{scans.source or 'scans'}: the odometry's turns agree best with the scans' at a delay of "
                f"{delays[best]:+.2f} s, the end of the ±{widest:g} s searched: the laser's and the odometry's "
                "clocks disagree by more, or the scans do not match (give --scan-delay SECONDS)"
            )
    delay = float(delays[best])
    if 0 < best < len(delays) - 1:
        lo, mid, hi = errors[best - 1 : best + 2]
        curvature = lo - 2 * mid + hi
        if curvature > 0:
            delay += step * 0.5 * (lo - hi) / curvature
    return ScanDelay(delay=float(delay), delays=delays, heading_error=errors, pairs=len(used))
