"""SLAM on range scans (paper sec. IV): the configuration (`config`), the particle filter's driver
(`driver`: which scans to integrate, the core's filter, a pose for every scan) and the scans'
timing against the odometry (`timing`)."""

from omnitof.slam.driver import SlamResult, dense_to_map, fill_trajectory, run_slam, select_scans

__all__ = ["SlamResult", "dense_to_map", "fill_trajectory", "run_slam", "select_scans"]
