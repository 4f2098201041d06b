"""One entry point for range-scan input: CARMEN logs and ROS bags with LaserScan + Odometry."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any
from pathlib import Path

from omnitof.errors import InputError
from omnitof.types import ScanSequence

# A ROS 2 bag is a folder (with metadata.yaml); single-file bags carry these suffixes.
BAG_SUFFIXES = {".bag", ".mcap", ".db3"}


@dataclass
class ScanInput:
    """Scans read from a file, and what the reader noticed."""

    scans: ScanSequence
    kind: str  # "carmen" or "rosbag"
    bad_lines: int = 0


def is_bag(path: Path) -> bool:
    return path.is_dir() or path.suffix in BAG_SUFFIXES


def is_tof_bag(path: str | Path) -> bool:
    """Whether `path` is a bag of ToF images (sensor_msgs/Image or CompressedImage) rather than
    of LaserScans."""
    path = Path(path)
    if not (path.exists() and is_bag(path)):
        return False
    from omnitof.io.rosbag import bag_message_types

    types = bag_message_types(path)
    return bool(types & {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage"}) and not types & {
        "sensor_msgs/msg/LaserScan", "sensor_msgs/msg/MultiEchoLaserScan"}


def read_scans(path: str | Path, *, skip_bad_lines: bool = False, laser_topics: Any = None) -> ScanInput:
    """Read scans with odometry from a CARMEN log (plain, .gz, .bz2) or a ROS 1/2 bag holding
    sensor_msgs/LaserScan and odometry (nav_msgs/Odometry, or the transform odom → base on /tf;
    topics found by type unless `laser_topics`, an `io.rosbag.LaserTopics`, names them)."""
    path = Path(path)
    if not path.exists():
        raise InputError("no such file or folder", path)
    if is_bag(path):
        from omnitof.io.rosbag import read_laserscan_bag

        return ScanInput(read_laserscan_bag(path, topics=laser_topics), "rosbag")
    from omnitof.io.carmen import read_carmen

    log = read_carmen(path, skip_bad_lines=skip_bad_lines)
    return ScanInput(log.scans, "carmen", log.bad_lines)
