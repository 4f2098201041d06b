"""Odometry that no robot makes: wheels that never turn, and jumps.

A log can carry odometry and still carry none that a filter can use, in two ways a user only
sees once the map is wrong:

- **Frozen**: every scan carries the same pose (a converted or hand-held log whose pose fields
  are zeros, a bag whose odometry topic was never updated). The filter integrates a scan only
  once the odometry says the robot moved (`filter.linear_update`), so the map would be the first
  scan alone. Such odometry is set aside and estimated from the scans, as `--ignore-odometry`
  does (omnitof.slam.scan_odometry); a robot that really stood still is estimated standing.
- **Jumps**: a base driver restarted mid-log (its odometry starts again at zero), or a pose
  written wrong once (a spike out and back). A step between two scans longer than `JUMP_MIN_M`
  and `JUMP_FACTOR` times the log's 99th percentile step, and faster than `MAX_SPEED`, is taken
  as no motion: the poses after it keep their motions relative to each other, and the scans on
  either side are matched across the step as after any other. The filter would otherwise put
  the rest of the log metres away, or fold it over the first half.

Both come with a warning naming the scans, and are recorded in summary.yaml.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np

from omnitof.errors import OmnitofWarning
from omnitof.geometry import compose, relative
from omnitof.types import ScanSequence

# The five benchmark logs' largest steps are 2.0-2.8 times their 99th percentile (Intel 0.22 m,
# MIT CSAIL 0.95 m at 0.21 s, ACES 0.38 m over a 3 s gap): a step ten times it, at least 2 m
# and faster than any indoor robot drives, is no motion of the robot's.
JUMP_FACTOR = 10.0
JUMP_MIN_M = 2.0
MAX_SPEED = 10.0  # m/s
# Poses that differ by less than this (m, rad) are one pose: written from the same numbers.
FROZEN_TOLERANCE = 1e-9


class OdometryWarning(OmnitofWarning):
    """The input's odometry was frozen or jumped, and was repaired before the filter."""


@dataclasses.dataclass(frozen=True)
class OdometryJump:
    """A step of the odometry taken as no motion: from scan `scan - 1` to `scan`."""

    scan: int
    time: float  # the stamp of scan `scan`
    metres: float
    degrees: float
    seconds: float  # between the two scans

    def to_dict(self) -> dict[str, float | int]:
        return {"scan": self.scan, "time": round(self.time, 6), "metres": round(self.metres, 3),
                "degrees": round(self.degrees, 2), "seconds": round(self.seconds, 3)}


def frozen_odometry(scans: ScanSequence) -> bool:
    """Whether the odometry of two or more scans never moves (see the module docstring)."""
    if not scans.odometry_known or len(scans) < 2:
        return False
    return bool(np.all(np.abs(scans.odometry - scans.odometry[0]) <= FROZEN_TOLERANCE))


def odometry_jumps(scans: ScanSequence) -> list[OdometryJump]:
    """The odometry's steps that no robot makes (see the module docstring), in scan order."""
    if not scans.odometry_known or len(scans) < 3:
        return []
    step = relative(scans.odometry[:-1], scans.odometry[1:])
    metres = np.hypot(step[:, 0], step[:, 1])
    dt = np.diff(scans.timestamps)
    positive = dt[dt > 0]
    # Stamps that jitter (Intel steps back 631 times) or repeat give no speed: the typical
    # interval stands in for an interval shorter than it.
    typical = float(np.median(positive)) if len(positive) else 0.0
    seconds = np.maximum(dt, typical)
    limit = max(JUMP_MIN_M, JUMP_FACTOR * float(np.quantile(metres, 0.99)))
    with np.errstate(divide="ignore"):
        fast = metres > MAX_SPEED * seconds
    found = np.flatnonzero((metres > limit) & fast)
    return [OdometryJump(scan=int(k) + 1, time=float(scans.timestamps[k + 1]), metres=float(metres[k]),
                         degrees=float(math.degrees(step[k, 2])), seconds=float(dt[k])) for k in found]


def without_jumps(odometry: np.ndarray, jumps: list[OdometryJump]) -> np.ndarray:
    """`odometry` (N, 3) with each jump's step taken as no motion: the poses from the jump's
    scan on keep their motions relative to each other and start where the scan before stands."""
    out = np.array(odometry, dtype=np.float64, copy=True)
    for jump in jumps:
        k = jump.scan
        out[k:] = compose(out[k - 1], relative(out[k], out[k:]))
    return out


def repair_odometry(scans: ScanSequence, source: str) -> tuple[ScanSequence, dict]:
    """`scans` with frozen odometry set aside (`odometry_known` False, so that SLAM estimates it
    from the scans) or its jumps taken as no motion, each with an OdometryWarning naming
    `source`; and a record for summary.yaml (empty where nothing was done)."""
    if frozen_odometry(scans):
        warnings.warn(OdometryWarning(
            f"{source}: the odometry never moves over its {len(scans)} scans (every pose is "
            f"{_pose_text(scans.odometry[0])}): set aside, and estimated from the scans as --ignore-odometry does"
        ), stacklevel=2)
        repaired = dataclasses.replace(scans, odometry_known=False,
                                       odometry_rule=f"none: the input's never moved ({scans.odometry_rule or 'as read'})")
        return repaired, {"frozen": True}
    jumps = odometry_jumps(scans)
    if not jumps:
        return scans, {}
    listed = "; ".join(f"{j.metres:.2f} m and {j.degrees:.1f}° in {j.seconds:.2f} s before scan {j.scan} "
                       f"(t = {j.time:.6f})" for j in jumps[:3])
    more = f"; and {len(jumps) - 3} more" if len(jumps) > 3 else ""
    warnings.warn(OdometryWarning(
        f"{source}: the odometry jumps as no robot moves ({listed}{more}): each such step is taken as no "
        "motion, and the scans are matched across it"
    ), stacklevel=2)
    repaired = dataclasses.replace(scans, odometry=without_jumps(scans.odometry, jumps))
    return repaired, {"jumps": [j.to_dict() for j in jumps]}


def _pose_text(pose: np.ndarray) -> str:
    return f"({pose[0]:g}, {pose[1]:g}, {pose[2]:g})"
