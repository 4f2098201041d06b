"""Where a bag's odometry comes from, shared by ToF bags (`tof`) and LaserScan bags (`laserscan`).

Robots record their odometry in one of three ways, and both readers take all three:

- nav_msgs/Odometry messages on a topic ("/odom" by convention);
- only the transform odom → base on /tf (tf2_msgs/TFMessage, or tf/tfMessage before ROS Hydro),
  which is what gmapping and slam_toolbox read;
- not at all (a lidar or camera carried by hand): the reader says so, and SLAM estimates the
  odometry from the scans (`omnitof.slam.scan_odometry`).

`read_bag_odometry` does it all in one call: `odometry_connections` decides which (from the
topic names a user gave, else by type), the Odometry messages are read in one pass with the
ground truth, and `read_tf_odometry` turns the transforms into a Trajectory. The 4×4 matrix of a transform
(`edge_matrix`) is here too, since the tf pass keeps the first of each transform for the
laser's mounting.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from rosbags.highlevel import AnyReader

from omnitof.errors import InputError
from omnitof.io.rosbag.common import (
    GROUND_TRUTH_TOPIC,
    ODOM_FRAME,
    ODOMETRY,
    TF_MESSAGE,
    TF_TOPIC,
    TF_TYPE_NAMES,
    TF_TYPES,
    RosbagWarning,
    _connections,
    _frame_name,
    _messages,
    _ns_to_s,
    _pick_topic,
    _planar_pose,
    _read_trajectories,
    _stamp_ns,
)
from omnitof.types import Trajectory

Edges = dict[str, tuple[str, np.ndarray]]  # child frame → (parent frame, parent_T_child 4×4)

# A hole in the odometry longer than both of these is taken for no odometry (a stale transform
# stamped long before the rest, a recording paused): frames in it are dropped like those outside
# its span, not given a pose interpolated across it. 10 intervals let a few lost messages pass
# (wheel odometry runs at 10-100 Hz); the 1 s floor keeps a sparse odometry (1 Hz) whole.
GAP_INTERVALS = 10
GAP_MIN_S = 1.0


class TopicsOption(NamedTuple):
    """How a reader's errors tell a user to name a topic or frame: the CLI option
    ("--laser-topics") and the Python class ("LaserTopics")."""

    option: str
    api: str

    def choose(self, role: str, value: str = "TOPIC") -> str:
        return f"{self.option} {role}={value} (in Python topics={self.api}({role}=...))"


class BagOdometry(NamedTuple):
    """What `read_bag_odometry` found.

    trajectory: the odometry by its own stamps, None where the bag has none.
    name: what errors call it: the topic, or "/tf (odom → base_link)"; "" without odometry.
    source: where it came from, in words: the topic, or "the transform odom → base_link on /tf".
    base: the robot's frame it moves (the Odometry messages' child_frame_id, the transform's
        child), None where unknown.
    ground_truth: the ground-truth topic's poses, where it has the Odometry type.
    first_edges: the first of each transform on the tf topic, where it was read (else None).
    """

    trajectory: Trajectory | None
    name: str
    source: str
    base: str | None
    ground_truth: Trajectory | None
    first_edges: Edges | None

    def rule(self, at: str, odom_frame: str, tf: str) -> str:
        """The odometry rule for a summary (`odometry_rule`)."""
        return odometry_rule(self.source, at, odom_frame, tf)


def odometry_rule(source: str, at: str, odom_frame: str, tf: str) -> str:
    """How each `at` ("scan", "frame") got its odometry pose, for a summary: interpolated from
    `source` (`BagOdometry.source`), or none where it is ""."""
    if not source:
        return f"none: the bag has no {ODOMETRY} topic and no transform {odom_frame} → base on {tf}"
    return f"interpolated from {source} at each {at}'s timestamp"


def read_bag_odometry(
    reader: AnyReader, path: Path, *, odometry: str | None, ground_truth: str, tf: str, odom_frame: str,
    base_frame: str | None, how: TopicsOption, find: bool = True,
) -> BagOdometry:
    """The bag's odometry (`odometry_connections`: an Odometry topic, the transform odom_frame →
    base on `tf`, or none; not looked for at all unless `find`) and its ground truth (Odometry
    messages on `ground_truth`, never the odometry's own topic), the Odometry messages of both
    read in one pass. A `ground_truth` or `tf` other than the default (`GROUND_TRUTH_TOPIC`,
    `TF_TOPIC`) was named by the user and must be in the bag; a default ground truth without
    messages is left out. Without odometry, `point_at_other_tf` says where it may be."""
    # A topic the user named must be there (a typo would silently lose it); a default may be absent.
    named_truth = ground_truth != GROUND_TRUTH_TOPIC
    if named_truth:
        _connections(reader, path, ground_truth, ODOMETRY)
    if tf != TF_TOPIC:
        _connections(reader, path, tf, TF_TYPE_NAMES)
    conns: list[Any] = []
    kind = "none"
    if find:
        conns, kind = odometry_connections(reader, path, odometry=odometry, ground_truth=ground_truth, tf=tf, how=how)
    truth = [c for c in reader.connections if c.topic == ground_truth and c.msgtype == ODOMETRY
             and not (kind == "odometry" and c.topic == conns[0].topic)]
    if not named_truth and not sum(c.msgcount for c in truth):
        truth = []  # declared but never published (ROS 2 bags record those): no ground truth
    trajectories = _read_trajectories(reader, path, (conns if kind == "odometry" else []) + truth)
    ground = trajectories.get(ground_truth) if truth else None
    if kind == "odometry":
        topic = conns[0].topic
        return BagOdometry(trajectories[topic], topic, topic, base_frame or trajectories.child_frames.get(topic),
                           ground, None)
    first = None
    if kind == "tf":
        found = read_tf_odometry(reader, path, conns, odom_frame, base_frame, how=how,
                                 required=tf_required(odometry, odom_frame, base_frame))
        first = found.first_edges if conns[0].topic == tf else None
        if found.trajectory is not None:
            topic = conns[0].topic
            return BagOdometry(found.trajectory, f"{topic} ({odom_frame} → {found.base})",
                               f"the transform {odom_frame} → {found.base} on {topic}", found.base, ground, first)
    if find:
        point_at_other_tf(reader, path, tf, odom_frame, how)
    return BagOdometry(None, "", "", base_frame, ground, first)


def spans_no_time(trajectory: Trajectory) -> bool:
    """Whether the odometry's poses all share one stamp (one message, or stamps left unset): it
    gives a pose at that instant only, so a frame at any other time is an InputError
    (`no_time_span`), not a frame to drop."""
    return bool(trajectory.timestamps[0] == trajectory.timestamps[-1])


def no_time_span(what: str, trajectory: Trajectory, at: str, path: Path) -> InputError:
    """The error for an odometry that spans no time (`spans_no_time`): `what` names it ("the
    odometry (/odom)"), `at` the frames it cannot give a pose for."""
    return InputError(f"{what} spans no time (every pose is stamped {trajectory.timestamps[0]:.9f} s: one message, "
                      f"or stamps left unset), so it gives no pose for {at}", path)


def scans_span_no_time(where: str, what: str, count: int, ns: int, path: Path) -> InputError:
    """The error for `count` (more than one) scans or frames at `where` (a topic) whose header
    stamps are all `ns`: stamps left unset, as by a node with use_sim_time and no /clock. Their
    order in time, their odometry poses and the scan delay all come from the stamps, so such a
    bag maps nothing but its first scan."""
    return InputError(f"{where}: the {count} {what} span no time (every one is stamped {_ns_to_s(ns):.9f} s): "
                      "their header stamps were left unset, as by a node with use_sim_time and no /clock; record "
                      "the bag with /clock published, or without use_sim_time", path)


def point_at_other_tf(reader: AnyReader, path: Path, tf: str, odom_frame: str, how: TopicsOption) -> None:
    """Where the bag gave no odometry: a RosbagWarning if a transform topic other than `tf` holds a
    transform from odom_frame (or a frame named like it), as a robot recording its odometry on
    /tf_odom has it, rather than let SLAM estimate an odometry the bag holds."""
    others = sorted({c.topic for c in reader.connections if c.topic != tf and c.msgtype in TF_TYPES and c.msgcount})
    for topic in others:
        for _, msg in _messages(reader, path, [c for c in reader.connections if c.topic == topic]):
            for transform in msg.transforms:
                parent, child = _frame_name(transform.header.frame_id), _frame_name(transform.child_frame_id)
                if parent == odom_frame or "odom" in parent:
                    option = f"odometry={topic}" + ("" if parent == odom_frame else f",odom_frame={parent}")
                    warnings.warn(
                        f"{path}: no {ODOMETRY} topic and no transform from the frame {odom_frame} on {tf}, so the "
                        f"odometry is taken as unknown and estimated from the scans; it may be the transform "
                        f"{parent} → {child} on {topic}: name it with {how.option} {option}",
                        RosbagWarning, stacklevel=4,
                    )
                    return


def time_span(trajectory: Trajectory) -> str:
    """A trajectory's time span for messages: "[first, last] s"."""
    return f"[{trajectory.timestamps[0]:.9f}, {trajectory.timestamps[-1]:.9f}] s"


def odometry_gaps(trajectory: Trajectory) -> np.ndarray:
    """(K, 2) [start, end] s of the odometry's holes: intervals between its stamps longer than
    GAP_MIN_S and GAP_INTERVALS times its median interval."""
    t = np.unique(trajectory.timestamps)
    if len(t) < 3:  # two stamps: the one interval is the usual one
        return np.zeros((0, 2))
    dt = np.diff(t)
    hole = np.flatnonzero(dt > max(GAP_MIN_S, GAP_INTERVALS * float(np.median(dt))))
    return np.column_stack([t[hole], t[hole + 1]])


def outside_odometry(trajectory: Trajectory, timestamps: np.ndarray) -> np.ndarray:
    """(N,) bool: the times outside the odometry's span or inside one of its holes
    (`odometry_gaps`), where it gives no pose."""
    t = np.asarray(timestamps, dtype=np.float64)
    outside = (t < trajectory.timestamps[0]) | (t > trajectory.timestamps[-1])
    for start, end in odometry_gaps(trajectory):
        outside |= (t > start) & (t < end)
    return outside


def odometry_coverage(trajectory: Trajectory) -> str:
    """Where the odometry gives poses, for messages: its time span, and its holes if any."""
    text = f"the odometry's time span {time_span(trajectory)}"
    gaps = odometry_gaps(trajectory)
    if len(gaps):
        listed = ", ".join(f"({a:.9f}, {b:.9f})" for a, b in gaps[:3]) + (", …" if len(gaps) > 3 else "")
        text += f" less its {len(gaps)} hole(s) without poses {listed} s"
    return text


def frames_without_slash(topics: Any) -> None:
    """Strip a leading slash from a frozen topics dataclass's `odom_frame` and `base_frame`: as
    `rosbag info` and ROS 1 bags show them, "/odom" names the frame "odom". ValueError naming
    the role where nothing is left of a name, or where both name one frame."""
    for name in ("odom_frame", "base_frame"):
        value = getattr(topics, name)
        if value is not None:
            frame = _frame_name(value)
            if not frame:
                raise ValueError(f"{name}={value!r} names no frame: nothing is left after its leading slashes")
            object.__setattr__(topics, name, frame)
    if topics.odom_frame == topics.base_frame:
        raise ValueError(f"odom_frame and base_frame are both {topics.odom_frame!r}: the odometry is the transform "
                         "from the one frame to the other")


def odometry_connections(
    reader: AnyReader, path: Path, *, odometry: str | None, ground_truth: str | None, tf: str, how: TopicsOption
) -> tuple[list[Any], str]:
    """The connections the odometry comes from and their kind: "odometry" (nav_msgs/Odometry),
    "tf" (a TFMessage topic), or "none" (no connections: the bag has neither, and none was
    named).

    `odometry` names the topic (an Odometry or a TFMessage topic); None: the one Odometry topic
    ("/odom" among several, never `ground_truth`, never one without messages), and where the bag
    has none, `tf`."""
    if odometry is not None:
        conns = [c for c in reader.connections if c.topic == odometry]
        if not conns:  # missing: the error lists what the bag has
            _connections(reader, path, odometry, (ODOMETRY, TF_MESSAGE))
        if all(c.msgtype in TF_TYPES for c in conns):
            return conns, "tf"
        if any(c.msgtype != ODOMETRY for c in conns):
            kinds = ", ".join(sorted({c.msgtype for c in conns}))
            raise InputError(f"topic {odometry} has type {kinds}, expected {ODOMETRY} or {TF_MESSAGE}", path)
        found = _connections(reader, path, odometry, ODOMETRY)
        assert found is not None  # required topics are never None
        return found, "odometry"
    # A topic declared but never published (ROS 2 bags record those) holds no odometry.
    counts: dict[str, int] = {}
    for c in reader.connections:
        counts[c.topic] = counts.get(c.topic, 0) + c.msgcount
    exclude = {ground_truth} if ground_truth else set()
    exclude |= {topic for topic, n in counts.items() if n == 0}
    if any(c.msgtype == ODOMETRY and c.topic not in exclude for c in reader.connections):
        return _pick_topic(reader, path, ODOMETRY, None, "/odom", how.choose("odometry"), exclude=exclude), "odometry"
    conns = [c for c in reader.connections if c.topic == tf and c.msgtype in TF_TYPES]
    return conns, "tf" if conns else "none"


class TfOdometry(NamedTuple):
    """What `read_tf_odometry` found: the odometry and its base frame (None where tf holds
    none), and the first of each transform on the topic (for a laser's mounting, where
    /tf_static lacks it: one pass over tf for both)."""

    trajectory: Trajectory | None
    base: str | None
    first_edges: Edges


def read_tf_odometry(
    reader: AnyReader, path: Path, connections: Sequence[Any], odom_frame: str, base_frame: str | None,
    *, required: bool, how: TopicsOption,
) -> TfOdometry:
    """The transform odom_frame → base as a Trajectory by the transforms' own stamps, with base
    `base_frame` or the one frame whose parent on tf is odom_frame. Out-of-order transforms are
    sorted (tf buffers them so); of several at one stamp the last is kept. Where tf holds no such
    transform: an InputError if `required`, else no trajectory (with a RosbagWarning where
    another frame named like an odometry frame is there)."""
    topic = connections[0].topic
    rows: dict[str, list[tuple[int, float, float, float]]] = {}
    first_edges: Edges = {}
    pairs: set[tuple[str, str]] = set()  # (parent, child) seen, for the error that lists them
    for _, msg in _messages(reader, path, connections):
        for tf in msg.transforms:
            parent, child = _frame_name(tf.header.frame_id), _frame_name(tf.child_frame_id)
            pairs.add((parent, child))
            if child not in first_edges:
                first_edges[child] = (parent, edge_matrix(tf))
            if parent != odom_frame or child == parent or (base_frame is not None and child != base_frame):
                continue  # not the odometry's (a frame to itself is no motion: tf2 ignores it too)
            ns = _stamp_ns(tf.header.stamp)
            pose = _planar_pose(tf.transform.translation, tf.transform.rotation,
                                f"topic {topic}: the transform {parent} → {child} stamped {_ns_to_s(ns):.9f} s", path)
            rows.setdefault(child, []).append((ns, *pose))
    if not rows and not required:
        parents = sorted({a for a, _ in pairs if "odom" in a})
        if parents:  # a PR2's odom_combined: say where the odometry may be, rather than estimate it
            warnings.warn(
                f"{path}: {topic} holds no transform from the frame {odom_frame}, so the odometry is taken as "
                f"unknown and estimated from the scans; it may be the transform from {', '.join(parents)}: "
                f"name it with {how.option} odom_frame=FRAME", RosbagWarning, stacklevel=4,
            )
        return TfOdometry(None, None, first_edges)
    if not rows:
        wanted = f"{odom_frame} → {base_frame}" if base_frame else f"from the frame {odom_frame}"
        listed = ", ".join(f"{a} → {b}" for a, b in sorted(pairs)[:20]) or "none"
        raise InputError(
            f"topic {topic}: no transform {wanted} for the odometry (name the frames with "
            f"{how.option} odom_frame=FRAME,base_frame=FRAME); its transforms: {listed}",
            path,
        )
    if len(rows) > 1:
        raise InputError(
            f"topic {topic}: the frame {odom_frame} moves several frames ({', '.join(sorted(rows))}); "
            f"choose the robot's with {how.choose('base_frame', 'FRAME')}",
            path,
        )
    (child, data), = rows.items()
    stamps = np.array([row[0] for row in data], dtype=np.int64)
    order = np.argsort(stamps, kind="stable")
    stamps = stamps[order]
    poses = np.array([row[1:] for row in data], dtype=np.float64)[order]
    last = np.append(stamps[1:] != stamps[:-1], True)  # the last published at each stamp
    seconds = np.array([_ns_to_s(int(ns)) for ns in stamps[last]], dtype=np.float64)
    return TfOdometry(Trajectory(seconds, poses[last]), child, first_edges)


def tf_required(odometry: str | None, odom_frame: str, base_frame: str | None) -> bool:
    """Whether a tf topic without the odometry's transform is an error: where the user named
    the odometry's topic or frames. Found by itself, it means a bag without odometry."""
    return odometry is not None or base_frame is not None or odom_frame != ODOM_FRAME


def edge_matrix(tf: Any) -> np.ndarray:
    """parent_T_child 4×4 of a geometry_msgs/TransformStamped."""
    t, q = tf.transform.translation, tf.transform.rotation
    matrix = np.eye(4)
    matrix[:3, :3] = rotation_matrix(q.x, q.y, q.z, q.w)
    matrix[:3, 3] = (t.x, t.y, t.z)
    return matrix


def rotation_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """The rotation of a quaternion of any length (zero: none; not finite: NaN, refused later)."""
    q = np.array([x, y, z, w], dtype=np.float64)
    if not np.isfinite(q).all():
        return np.full((3, 3), np.nan)
    if not q.any():
        return np.eye(3)
    q /= np.abs(q).max()  # first, so that the norm of huge components does not overflow
    x, y, z, w = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
