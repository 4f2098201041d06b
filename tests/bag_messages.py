"""ROS messages and bags written message by message with rosbags, as another tool would write
them: the helpers that tests/test_rosbag.py and tests/test_rosbag_odometry_inputs.py share."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from omnitof.io.rosbag import RosbagWarning, read_laserscan_bag
from omnitof.types import ScanSequence

HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
NOETIC.register(
    get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage")
)
OLD_TF = "tf/msg/tfMessage"  # ROS 1 before Hydro: the same fields
NOETIC.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", OLD_TF))
ODOM = "nav_msgs/msg/Odometry"
SCAN = "sensor_msgs/msg/LaserScan"
TF = "tf2_msgs/msg/TFMessage"
NS = 1_000_000_000


def ros_time(store, ns: int):
    return store.types["builtin_interfaces/msg/Time"](sec=ns // NS, nanosec=ns % NS)


def header(store, ns: int, frame_id: str):
    cls = store.types["std_msgs/msg/Header"]
    if store is NOETIC:
        return cls(seq=0, stamp=ros_time(store, ns), frame_id=frame_id)
    return cls(stamp=ros_time(store, ns), frame_id=frame_id)


def odometry_msg(store, ns: int, pose, child: str = "base_link", q=None):
    """pose (x, y, yaw); q (qx, qy, qz, qw), where given, is the orientation instead of yaw's."""
    t = store.types
    q = (0.0, 0.0, math.sin(pose[2] / 2), math.cos(pose[2] / 2)) if q is None else q
    vec = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return t[ODOM](
        header=header(store, ns, "odom"),
        child_frame_id=child,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=t["geometry_msgs/msg/Pose"](
                position=t["geometry_msgs/msg/Point"](x=pose[0], y=pose[1], z=0.0),
                orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
            covariance=np.zeros(36),
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](linear=vec, angular=vec), covariance=np.zeros(36)
        ),
    )


def scan_msg(store, ns: int, ranges, *, frame="laser", angle_min=-1.0, inc=0.5, rmin=0.1, rmax=4.0):
    return store.types[SCAN](
        header=header(store, ns, frame),
        angle_min=angle_min,
        angle_max=angle_min + inc * (len(ranges) - 1),
        angle_increment=inc,
        time_increment=0.0,
        scan_time=0.0,
        range_min=rmin,
        range_max=rmax,
        ranges=np.asarray(ranges, dtype=np.float32),
        intensities=np.zeros(0, dtype=np.float32),
    )


def tf_msg(store, transforms, ns: int = 0, msgtype: str = TF):
    """transforms: (parent, child, (x, y, z), (qx, qy, qz, qw)) tuples, all stamped `ns`."""
    t = store.types
    return t[msgtype](
        transforms=[
            t["geometry_msgs/msg/TransformStamped"](
                header=header(store, ns, parent),
                child_frame_id=child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](x=xyz[0], y=xyz[1], z=xyz[2]),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
                ),
            )
            for parent, child, xyz, q in transforms
        ]
    )


def write_raw(path: Path, messages: list[tuple[str, str, object]], *, ros1: bool = False,
              declared: list[tuple[str, str]] = ()) -> Path:  # fmt: skip
    """A bag of (topic, msgtype, message), in this order (log times 1, 2, 3, … µs), and the
    topics `declared` (topic, msgtype) without a message."""
    store = NOETIC if ros1 else HUMBLE
    writer = Writer1(path) if ros1 else Writer2(path, version=9, storage_plugin=StoragePlugin.MCAP)
    with writer:
        conns = {topic: writer.add_connection(topic, msgtype, typestore=store) for topic, msgtype in declared}
        for k, (topic, msgtype, msg) in enumerate(messages):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            data = store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)
            writer.write(conns[topic], (k + 1) * 1000, data)
    return path


def read_warned(path: Path, **kwargs) -> tuple[ScanSequence, list[str]]:
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        scans = read_laserscan_bag(path, **kwargs)
    assert all(issubclass(w.category, RosbagWarning) for w in record)
    return scans, [str(w.message) for w in record]
