"""SLAM on range scans (paper sec. IV): the configuration (`config`), the particle filter's driver
(`driver`: which scans to integrate, the core's filter, a pose for every scan), what a
configuration implies for a log before it runs (`limits`: memory, submap size) and the scans'
timing against the odometry (`timing`)."""

from omnitof.slam.driver import SlamResult, dense_to_map, fill_trajectory, run_slam, select_scans
from omnitof.slam.limits import check_limits

__all__ = ["SlamResult", "check_limits", "dense_to_map", "fill_trajectory", "run_slam", "select_scans"]
