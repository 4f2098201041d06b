"""ROS 1 and ROS 2 bags: ToF sequences (images, camera info, odometry) and planar laser scans.

Everything goes through `rosbags` (pure Python; no ROS installation is needed). Two kinds of bag,
one submodule each, on shared machinery:

- `tof`: **ToF bags** (`write_tof_bag`, `read_tof_bag` → `ToFBag`, frames as
  `ToFFrameStamped`, topic names in `ToFTopics`): a ROS 2 bag folder with distance, amplitude
  and optional raw-sample images, camera info and odometry; its docstring has the layout.
- `laserscan`: **Laser-scan bags** (`read_laserscan_bag`, `write_laserscan_bag`, topic and
  frame names in `LaserTopics`): ROS 1 (`.bag` files) or ROS 2 bags with sensor_msgs/LaserScan
  and odometry (nav_msgs/Odometry, or the transform odom → base on /tf), read into a
  ScanSequence.
- `odometry`: where a bag's odometry comes from, for both: an Odometry topic, the transform
  odom → base on /tf, or none.
- `common`: what both use: opening bags (`bag_message_types`), message types and typestores,
  time conversions (`to_ros_time`, `from_ros_time`), the sidecar `<bag>/omnitof.yaml`
  (`SIDECAR_NAME`), the all-or-nothing write (`BagExistsError`), odometry read into
  Trajectories, `RosbagWarning`.

Every public name is importable from here (`from omnitof.io.rosbag import write_tof_bag`).
Units and frames follow omnitof.types: metres, radians, seconds; θ counter-clockwise from +x;
a range of +inf means no echo.
"""

from omnitof.geometry import interpolate_poses
from omnitof.io.rosbag.common import (
    DEFAULT_STORAGE,
    SIDECAR_NAME,
    BagExistsError,
    RosbagWarning,
    bag_message_types,
    checked_bag_target,
    from_ros_time,
    to_ros_time,
)
from omnitof.io.rosbag.laserscan import LaserTopics, read_laserscan_bag, write_laserscan_bag
from omnitof.io.rosbag.tof import (
    ToFBag,
    ToFFrameStamped,
    ToFTopics,
    read_tof_bag,
    write_tof_bag,
)

__all__ = [
    "DEFAULT_STORAGE",
    "SIDECAR_NAME",
    "BagExistsError",
    "LaserTopics",
    "RosbagWarning",
    "ToFBag",
    "ToFFrameStamped",
    "ToFTopics",
    "bag_message_types",
    "checked_bag_target",
    "from_ros_time",
    "interpolate_poses",
    "read_laserscan_bag",
    "read_tof_bag",
    "to_ros_time",
    "write_laserscan_bag",
    "write_tof_bag",
]
