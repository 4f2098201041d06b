"""The plain data types that pass between omnitof's stages.

Conventions (see docs/conventions.md): metres, radians, seconds; poses (x, y, theta) with theta
counter-clockwise from +x; a range of +inf means "no echo / no reading" (never zero, never NaN).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# The largest float32: what the binary formats that store float32 (PLY points, LaserScan ranges)
# can hold; their writers refuse larger values rather than write inf.
FLOAT32_MAX = float(np.finfo(np.float32).max)


def first_non_finite(*arrays: np.ndarray) -> int | None:
    """The first row at which any of `arrays` ((N,) or (N, k) each, N shared) holds a value
    that is not finite; None where every row is finite. Every check of stamps and poses uses it,
    so that each names the first bad row the same way."""
    if len(arrays[0]) == 0:
        return None
    bad = np.zeros(len(arrays[0]), dtype=bool)
    for values in arrays:
        values = np.asarray(values)
        bad |= ~np.isfinite(values).reshape(len(values), -1).all(axis=1)
    return int(np.argmax(bad)) if bad.any() else None


@dataclass
class ScanSequence:
    """A stream of planar range scans with the odometry pose of the robot at each scan.

    Beam geometry. Most sensors keep one geometry: `angles` is (B,) and every scan has its B
    beams. Some change it from scan to scan (CARMEN ROBOTLASER and ROS LaserScan messages state
    it per scan; the Freiburg hospital's interlaced SICK alternates 181 beams from -90° with 180
    beams from -89.75°, -89.5° or -89.25°): then `angles` is (N, B), B the largest beam count,
    and `beam_counts[i]` says how many beams scan i has. Its beams are the first beam_counts[i]
    columns of angles[i] and ranges[i]; the columns after them are padding (angles NaN, ranges
    +inf, remissions 0) and never used. `scan_angles(i)` and `scan_ranges(i)` give one scan's
    beams without padding: use them wherever a single scan's beams are needed.

    Attributes:
        timestamps: (N,) float64, seconds, in the order the scans were taken. Real logs may step
            back a little where their clock did (the Intel log does; see io.carmen).
        ranges: (N, B) float32, metres; +inf where the beam returned no echo (and in padding).
        angles: (B,) float64, bearing of each beam in the sensor frame, radians, counter-clockwise
            from the sensor's +x axis (the driving direction for a forward-facing laser); or
            (N, B), one row per scan, for per-scan geometry (see above).
        odometry: (N, 3) float64, the robot's odometry pose (x, y, theta) at each scan.
        sensor_pose: (3,) float64, robot_T_sensor: the sensor's pose in the robot frame.
        max_range: the sensor's maximum range in metres; readings at or beyond it are no echo.
        remissions: (N, B) float32 or None, reflectance values where the log has them.
        ground_truth: (N, 3) float64 or None, true robot poses where known (simulation).
        source: where the data came from (a file name), for messages and reports.
        beam_counts: (N,) int64 for per-scan geometry (None for a fixed one; given None with
            (N, B) angles, every scan has B beams).
        max_range_rule: how max_range was found (a reader says which rule it applied, e.g.
            "PARAM robot_front_laser_max = 80.99"), for reports.
        repeated_scans_dropped: how many scans the reader dropped because each repeated the
            scan before it exactly (`drop_repeated_scans`), for reports.
        odometry_rule: how the reader found each scan's odometry pose (as logged with the scan,
            or interpolated from an odometry stream at its timestamp), for reports.
        odometry_known: False where the input has no odometry (a bag of a lidar alone) or it was
            set aside: then only `odometry[0]` counts (where the estimate starts; zeros from a
            reader), and SLAM estimates the odometry from the scans first
            (omnitof.slam.scan_odometry).
    """

    timestamps: np.ndarray
    ranges: np.ndarray
    angles: np.ndarray
    odometry: np.ndarray
    sensor_pose: np.ndarray = field(default_factory=lambda: np.zeros(3))
    max_range: float = 80.0
    remissions: np.ndarray | None = None
    ground_truth: np.ndarray | None = None
    source: str = ""
    beam_counts: np.ndarray | None = None
    max_range_rule: str = ""
    repeated_scans_dropped: int = 0
    odometry_rule: str = ""
    odometry_known: bool = True

    def __post_init__(self) -> None:
        self.timestamps = np.ascontiguousarray(self.timestamps, dtype=np.float64)
        self.ranges = np.ascontiguousarray(self.ranges, dtype=np.float32)
        self.angles = np.ascontiguousarray(self.angles, dtype=np.float64)
        self.odometry = np.ascontiguousarray(self.odometry, dtype=np.float64)
        self.sensor_pose = np.ascontiguousarray(self.sensor_pose, dtype=np.float64)
        n = len(self.timestamps)
        if self.angles.ndim not in (1, 2):
            raise ValueError(f"angles must have shape (beams,) or (scans, beams), got {self.angles.shape}")
        beams = self.angles.shape[-1]
        if self.angles.ndim == 2 and self.angles.shape[0] != n:
            raise ValueError(f"per-scan angles must have shape (scans, beams) = ({n}, B), got {self.angles.shape}")
        if self.ranges.ndim != 2 or self.ranges.shape != (n, beams):
            raise ValueError(
                f"ranges must have shape (scans, beams) = ({n}, {beams}), got {self.ranges.shape}"
            )
        if self.odometry.shape != (n, 3):
            raise ValueError(f"odometry must have shape ({n}, 3), got {self.odometry.shape}")
        if self.sensor_pose.shape != (3,):
            raise ValueError(f"sensor_pose must have shape (3,), got {self.sensor_pose.shape}")
        if self.ground_truth is not None:
            self.ground_truth = np.ascontiguousarray(self.ground_truth, dtype=np.float64)
            if self.ground_truth.shape != (n, 3):
                raise ValueError(f"ground_truth must have shape ({n}, 3)")
        # Every reader refuses these; a NaN stamp or pose made in Python ran through SLAM into
        # the trajectory, and a NaN there fails only the file written at the end.
        for name in ("timestamps", "odometry", "sensor_pose", "ground_truth"):
            values = getattr(self, name)
            first = None if values is None else first_non_finite(values)
            if first is not None:
                raise ValueError(f"{name} must be finite; entry {first} is {values[first]}")
        if self.remissions is not None:
            self.remissions = np.ascontiguousarray(self.remissions, dtype=np.float32)
            if self.remissions.shape != self.ranges.shape:
                raise ValueError("remissions must have the shape of ranges")
        if self.angles.ndim == 1:
            if self.beam_counts is not None:
                raise ValueError("beam_counts needs per-scan angles (scans, beams)")
        else:
            self._check_per_scan_geometry()

    def _check_per_scan_geometry(self) -> None:
        """Check the beam counts and set the padding to NaN angles, +inf ranges, 0 remissions
        (on copies: the caller's arrays are not changed)."""
        n, beams = self.ranges.shape
        if self.beam_counts is None:
            self.beam_counts = np.full(n, beams, dtype=np.int64)
        counts = np.asarray(self.beam_counts)
        if counts.shape != (n,) or not np.issubdtype(counts.dtype, np.integer):
            raise ValueError(f"beam_counts must be ({n},) whole numbers, got {counts.dtype} {counts.shape}")
        if n and (counts.min() < 0 or counts.max() > beams):
            raise ValueError(f"beam_counts must lie in 0..{beams} (the columns of angles)")
        self.beam_counts = counts.astype(np.int64)
        used = self.beam_mask
        if not np.isfinite(self.angles[used]).all():
            raise ValueError("angles must be finite for every beam a scan has")
        pad = ~used
        if not pad.any():
            return
        if not np.isnan(self.angles[pad]).all():
            self.angles = self.angles.copy()
            self.angles[pad] = np.nan
        if not np.isposinf(self.ranges[pad]).all():
            self.ranges = self.ranges.copy()
            self.ranges[pad] = np.inf
        if self.remissions is not None and np.any(self.remissions[pad] != 0):
            self.remissions = self.remissions.copy()
            self.remissions[pad] = 0.0

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def per_scan_geometry(self) -> bool:
        """Whether each scan has its own beams (angles (N, B), beam_counts) or all share angles (B,)."""
        return self.angles.ndim == 2

    @property
    def n_beams(self) -> int:
        """Columns of `ranges`: the beam count, or the largest one for per-scan geometry."""
        return self.ranges.shape[1]

    @property
    def beam_mask(self) -> np.ndarray:
        """(N, B) bool: True where an entry of `ranges` is a beam of its scan, False in padding."""
        if self.beam_counts is None:
            return np.ones(self.ranges.shape, dtype=bool)
        return np.arange(self.n_beams) < self.beam_counts[:, None]

    def scan_angles(self, i: int) -> np.ndarray:
        """(B_i,) bearings of scan i's beams (sensor frame, radians)."""
        if self.beam_counts is None:
            return self.angles
        return self.angles[i, : self.beam_counts[i]]

    def scan_ranges(self, i: int) -> np.ndarray:
        """(B_i,) ranges of scan i (metres, +inf = no echo), one per `scan_angles(i)`."""
        if self.beam_counts is None:
            return self.ranges[i]
        return self.ranges[i, : self.beam_counts[i]]

    def slice(self, start: int | None = None, stop: int | None = None) -> "ScanSequence":
        """The scans start..stop (a view-free copy with the same metadata)."""
        return self.take(np.s_[start:stop])

    def take(self, s: slice | np.ndarray) -> "ScanSequence":
        """The scans a slice, index array or boolean mask selects, in that order (a copy with the
        same metadata)."""
        per_scan = self.per_scan_geometry
        return ScanSequence(
            timestamps=self.timestamps[s].copy(),
            ranges=self.ranges[s].copy(),
            angles=self.angles[s].copy() if per_scan else self.angles,
            odometry=self.odometry[s].copy(),
            sensor_pose=self.sensor_pose,
            max_range=self.max_range,
            remissions=None if self.remissions is None else self.remissions[s].copy(),
            ground_truth=None if self.ground_truth is None else self.ground_truth[s].copy(),
            source=self.source,
            beam_counts=self.beam_counts[s].copy() if per_scan else None,
            max_range_rule=self.max_range_rule,
            repeated_scans_dropped=self.repeated_scans_dropped,
            odometry_rule=self.odometry_rule,
            odometry_known=self.odometry_known,
        )

    def time_order(self) -> dict[str, int]:
        """How the timestamps run, for reports: `equal_stamps` scans stamped exactly as the one
        before them, `backward_steps` scans stamped earlier than it (see `drop_repeated_scans`
        for what the readers do with them), and the `repeated_scans_dropped` by the reader."""
        steps = np.diff(self.timestamps)
        return {
            "repeated_scans_dropped": int(self.repeated_scans_dropped),
            "equal_stamps": int(np.count_nonzero(steps == 0)),
            "backward_steps": int(np.count_nonzero(steps < 0)),
        }


def drop_repeated_scans(scans: ScanSequence) -> ScanSequence:
    """`scans` without the scans that repeat the scan before them exactly (same timestamp, same
    beams and readings, same odometry pose), with their number in `repeated_scans_dropped`.

    What equal timestamps mean, decided here for every reader: a scan that repeats its
    predecessor in every number is the same message logged twice (a logger or a bag recorded
    from two connections), not a second reading, so it is dropped. A scan stamped like its
    predecessor that reads differently is a real reading whose stamp jittered onto the
    previous one: it is kept in file order with its stamp, like the small backward steps of
    real logs (docs/conventions.md), and counted by `ScanSequence.time_order`. Outputs indexed
    by time (TUM files) then hold one pose per stamp (`omnitof.io.tum.write_tum`).
    """
    if len(scans) < 2:
        return scans
    same = scans.timestamps[1:] == scans.timestamps[:-1]
    same &= np.all(scans.odometry[1:] == scans.odometry[:-1], axis=1)
    same &= np.all(scans.ranges[1:] == scans.ranges[:-1], axis=1)  # +inf == +inf: no echo alike
    if scans.per_scan_geometry:
        a, b = scans.angles[1:], scans.angles[:-1]
        same &= np.all((a == b) | (np.isnan(a) & np.isnan(b)), axis=1)  # NaN: padding alike
    if scans.remissions is not None:
        same &= np.all(scans.remissions[1:] == scans.remissions[:-1], axis=1)
    if not same.any():
        return scans
    kept = scans.take(np.concatenate([[True], ~same]))
    kept.repeated_scans_dropped = scans.repeated_scans_dropped + int(same.sum())
    return kept


# Beam angles beyond this (rad) are no laser's (first and last beam; ±2π admits both the
# [-π, π) and the [0, 2π) conventions). The readers refuse them.
MAX_BEAM_ANGLE = 2.0 * math.pi + 1e-9
# Beams closer than this (rad) are one bearing: 2π in 6e8 beams (the densest scans read here
# hold 2e6: BENCHMARKS.md, "A log of very dense scans"). The readers refuse them.
MIN_BEAM_STEP = 1e-8
# Timestamps are seconds, a count from 0 or Unix times (~1.7e9): beyond 1e12 s (31 700 years)
# they are another unit (Unix milliseconds ~1.7e12, nanoseconds ~1.7e18) or a broken clock, and
# every tolerance in seconds would be read in that unit. The readers refuse them.
MAX_TIMESTAMP = 1e12
# The largest backwards step (s) of scan stamps the readers keep (in file order, with a warning):
# stamps jitter (Intel's step back 631 times by up to 0.6 s); beyond it a clock was set back.
MAX_TIME_REVERSAL = 1.0


def evenly_spaced_beams(
    starts: np.ndarray, steps: np.ndarray, counts: np.ndarray, *, tolerance: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """ScanSequence `angles` and `beam_counts` of scans whose beam j lies at starts[i] + j·steps[i]:
    (B,) and None when every scan has the first one's beams (same count; first and last beam
    within `tolerance` rad), else (N, B) padded with NaN and the counts (N,)."""
    starts = np.asarray(starts, dtype=np.float64)
    steps = np.asarray(steps, dtype=np.float64)
    counts = np.asarray(counts, dtype=np.int64)
    last = starts + steps * (counts - 1)
    if (
        np.all(counts == counts[0])
        and np.abs(starts - starts[0]).max() <= tolerance
        and np.abs(last - last[0]).max() <= tolerance
    ):
        return starts[0] + steps[0] * np.arange(counts[0]), None
    columns = np.arange(counts.max())
    angles = starts[:, None] + steps[:, None] * columns
    angles[columns >= counts[:, None]] = np.nan
    return angles, counts


def pad_rows(rows: list[np.ndarray], fill: float, dtype: type) -> np.ndarray:
    """(N, B) array of rows of different lengths (B the longest), `fill` after each row's end."""
    counts = np.array([len(r) for r in rows], dtype=np.int64)
    out = np.full((len(rows), int(counts.max(initial=0))), fill, dtype=dtype)
    out[np.arange(out.shape[1]) < counts[:, None]] = np.concatenate(rows) if rows else []
    return out


@dataclass
class Trajectory:
    """Timestamped planar poses: timestamps (N,) float64 and poses (N, 3) float64."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.ascontiguousarray(self.timestamps, dtype=np.float64)
        poses = np.ascontiguousarray(self.poses, dtype=np.float64)
        if self.timestamps.ndim != 1:
            raise ValueError(f"a trajectory's timestamps must be one-dimensional, got shape {self.timestamps.shape}")
        if poses.ndim == 1 and poses.size % 3 == 0:  # flat (x, y, theta, x, y, theta, ...)
            poses = poses.reshape(-1, 3)
        if poses.ndim != 2 or poses.shape[1] != 3:
            raise ValueError(f"a trajectory's poses must have shape (N, 3) (x, y, theta), got {poses.shape}")
        self.poses = poses
        if len(self.timestamps) != len(self.poses):
            raise ValueError("a trajectory needs one timestamp per pose")

    def __len__(self) -> int:
        return len(self.timestamps)


@dataclass
class OccupancyMap:
    """A 2D occupancy grid.

    `log_odds[row, col]` is the log-odds of occupancy of the cell whose lower-left corner is at
    origin + (col, row) * resolution: row 0 is the *lowest* y (the ROS map writer flips it so that
    row 0 of the image is at the top). `known[row, col]` is False where the cell was never observed.
    """

    log_odds: np.ndarray
    known: np.ndarray
    resolution: float
    origin: tuple[float, float]

    @property
    def probability(self) -> np.ndarray:
        """Occupancy probability per cell (0.5 where unknown)."""
        return 1.0 - 1.0 / (1.0 + np.exp(self.log_odds.astype(np.float64)))

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(xmin, xmax, ymin, ymax) in metres, for plotting."""
        h, w = self.log_odds.shape
        x0, y0 = self.origin
        return (x0, x0 + w * self.resolution, y0, y0 + h * self.resolution)
