"""The plain data types that pass between omnitof's stages.

Conventions (see docs/conventions.md): metres, radians, seconds; poses (x, y, theta) with theta
counter-clockwise from +x; a range of +inf means "no echo / no reading" (never zero, never NaN).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class ScanSequence:
    """A stream of planar range scans with the odometry pose of the robot at each scan.

    Attributes:
        timestamps: (N,) float64, seconds, in the order the scans were taken. Real logs may step
            back a little where their clock did (the Intel log does; see io.carmen).
        ranges: (N, B) float32, metres; +inf where the beam returned no echo.
        angles: (B,) float64, bearing of each beam in the sensor frame, radians, counter-clockwise
            from the sensor's +x axis (the driving direction for a forward-facing laser).
        odometry: (N, 3) float64, the robot's odometry pose (x, y, theta) at each scan.
        sensor_pose: (3,) float64, robot_T_sensor: the sensor's pose in the robot frame.
        max_range: the sensor's maximum range in metres; readings at or beyond it are no echo.
        remissions: (N, B) float32 or None, reflectance values where the log has them.
        ground_truth: (N, 3) float64 or None, true robot poses where known (simulation).
        source: where the data came from (a file name), for messages and reports.
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

    def __post_init__(self) -> None:
        self.timestamps = np.ascontiguousarray(self.timestamps, dtype=np.float64)
        self.ranges = np.ascontiguousarray(self.ranges, dtype=np.float32)
        self.angles = np.ascontiguousarray(self.angles, dtype=np.float64)
        self.odometry = np.ascontiguousarray(self.odometry, dtype=np.float64)
        self.sensor_pose = np.ascontiguousarray(self.sensor_pose, dtype=np.float64)
        n = len(self.timestamps)
        if self.ranges.ndim != 2 or self.ranges.shape != (n, len(self.angles)):
            raise ValueError(
                f"ranges must have shape (scans, beams) = ({n}, {len(self.angles)}), "
                f"got {self.ranges.shape}"
            )
        if self.odometry.shape != (n, 3):
            raise ValueError(f"odometry must have shape ({n}, 3), got {self.odometry.shape}")
        if self.sensor_pose.shape != (3,):
            raise ValueError(f"sensor_pose must have shape (3,), got {self.sensor_pose.shape}")
        if self.ground_truth is not None:
            self.ground_truth = np.ascontiguousarray(self.ground_truth, dtype=np.float64)
            if self.ground_truth.shape != (n, 3):
                raise ValueError(f"ground_truth must have shape ({n}, 3)")
        if self.remissions is not None:
            self.remissions = np.ascontiguousarray(self.remissions, dtype=np.float32)
            if self.remissions.shape != self.ranges.shape:
                raise ValueError("remissions must have the shape of ranges")

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def n_beams(self) -> int:
        return len(self.angles)

    def scan_angles(self, i: int) -> np.ndarray:
        """(B_i,) bearings of scan i's beams (sensor frame, radians)."""
        return self.angles

    def scan_ranges(self, i: int) -> np.ndarray:
        """(B_i,) ranges of scan i (metres, +inf = no echo), one per `scan_angles(i)`."""
        return self.ranges[i]

    def slice(self, start: int | None = None, stop: int | None = None) -> "ScanSequence":
        """The scans start..stop (a view-free copy with the same metadata)."""
        s = np.s_[start:stop]
        return ScanSequence(
            timestamps=self.timestamps[s].copy(),
            ranges=self.ranges[s].copy(),
            angles=self.angles,
            odometry=self.odometry[s].copy(),
            sensor_pose=self.sensor_pose,
            max_range=self.max_range,
            remissions=None if self.remissions is None else self.remissions[s].copy(),
            ground_truth=None if self.ground_truth is None else self.ground_truth[s].copy(),
            source=self.source,
        )


@dataclass
class Trajectory:
    """Timestamped planar poses: timestamps (N,) float64 and poses (N, 3) float64."""

    timestamps: np.ndarray
    poses: np.ndarray

    def __post_init__(self) -> None:
        self.timestamps = np.ascontiguousarray(self.timestamps, dtype=np.float64)
        self.poses = np.ascontiguousarray(self.poses, dtype=np.float64).reshape(-1, 3)
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
