"""The bag access shared by ToF bags (`tof`) and LaserScan bags (`laserscan`).

Everything goes through `rosbags` (pure Python; no ROS installation is needed): opening a bag
of any kind for reading (`bag_message_types`, and the private helpers that open a reader,
stream decoded messages and pick topics by name or type), the message types (`IMAGE`,
`ODOMETRY`, ...) and typestores (ROS 2 Humble, ROS 1 Noetic), header and Odometry messages,
nav_msgs/Odometry topics read into Trajectories, the sidecar file and the atomic write.

ROS 2 bags are written with MCAP storage by default (`DEFAULT_STORAGE`; "sqlite3" on request),
rosbag2 metadata version 8. Odometry poses are planar: position (x, y, 0), orientation the
quaternion of a rotation by θ about +z, covariances and twist left zero (unknown).

The sidecar YAML (true mirror geometry, camera, world name: whatever dict the caller gives) is
stored *inside* the bag folder as `<bag>/omnitof.yaml` (`SIDECAR_NAME`), so that it travels with
the bag and is written by the same final rename; ROS 2 tools ignore files they do not list in
metadata.yaml. A bag given as a single file (a ROS 1 `.bag`, a bare `.mcap`) has its sidecar
beside it as `<file>.omnitof.yaml`.

Writing is all-or-nothing: a bag is written under a hidden temporary name beside its target
(`.<name>.<random>.tmp/`) and renamed into place only when complete, so an interrupted write
leaves no valid-looking bag. Times are ROS times (sec, nanosec) made from float seconds with
`to_ros_time` (nearest nanosecond) and read back with `from_ros_time`; they must lie in
[0, 2**31) s (ROS 2 stamps hold int32 seconds).
Units and frames follow omnitof.types: metres, radians, seconds; θ counter-clockwise from +x.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from omnitof.errors import (
    InputError, OmnitofError, OmnitofWarning, OutputError, dump_yaml, load_yaml, read_problem, yaml_problem,
)
from omnitof.geometry import check_headings, quaternion_to_yaw, yaw_to_quaternion
from omnitof.interrupts import deferred_signals
from omnitof.io.atomic import BAG, check_replaceable, fsync_dir, replaceable_place, temporary_folder
from omnitof.io.plain import to_plain
from omnitof.types import Trajectory, first_non_finite

__all__ = [
    "DEFAULT_STORAGE",
    "SIDECAR_NAME",
    "SIDECAR_VERSION",
    "BagExistsError",
    "RosbagWarning",
    "bag_message_types",
    "sidecar_path",
    "checked_bag_target",
    "from_ros_time",
    "to_ros_time",
]

# rosbags writes MCAP since 0.10; fall back to sqlite3 with an older one.
DEFAULT_STORAGE = "mcap" if hasattr(StoragePlugin, "MCAP") else "sqlite3"
SIDECAR_NAME = "omnitof.yaml"
# The sidecar's format (its `omnitof_sidecar` field; sim.sequence.rig_sidecar writes it).
SIDECAR_VERSION = 1

# rosbag2 metadata version 8 is read by ROS 2 Iron and later; rosbags writes 8 or 9 only.
_ROSBAG2_VERSION: Literal[8] = 8

IMAGE = "sensor_msgs/msg/Image"
# Images as image_transport records them compressed ("compressed": PNG or JPEG;
# "compressedDepth": a 12-byte header and a 16-bit PNG).
COMPRESSED_IMAGE = "sensor_msgs/msg/CompressedImage"
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
# A laser's scans with every echo of each beam (Cartographer's backpack bags); read as its first.
MULTI_ECHO_SCAN = "sensor_msgs/msg/MultiEchoLaserScan"
LASER_TYPES = (LASER_SCAN, MULTI_ECHO_SCAN)
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
# The types read as tf: ROS 1 bags recorded before Hydro carry tf/tfMessage, the same fields.
TF_TYPE_NAMES = (TF_MESSAGE, "tf/msg/tfMessage")  # in the order errors list them
TF_TYPES = frozenset(TF_TYPE_NAMES)

# Frame ids written into headers (REP 105 names where there is one).
ODOM_FRAME = "odom"
WORLD_FRAME = "world"
BASE_FRAME = "base_link"
CAMERA_FRAME = "tof_optical_frame"
LASER_FRAME = "laser"

# The readers' default topics for the ground truth and the transforms. A topic set to anything
# else was named by the user, and must be in the bag; a default one may be absent.
GROUND_TRUTH_TOPIC = "/ground_truth"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

_NS = 1_000_000_000
_LISTED_TOPICS = 20  # how many topics an error message lists


class BagExistsError(OmnitofError, FileExistsError):
    """The target of a bag writer exists and `overwrite` was not given."""


class RosbagWarning(OmnitofWarning):
    """Data read from a bag were usable but not as expected (dropped scans, no laser pose)."""


# --- time ----------------------------------------------------------------------------------


def to_ros_time(t: float) -> tuple[int, int]:
    """(sec, nanosec) of a time in float seconds, to the nearest nanosecond; t must lie in
    [0, 2**31) s.

    The whole seconds are split off exactly before rounding, so epoch times (~1.7e9 s) keep the
    full precision of their float.
    """
    return divmod(_to_ns(t), _NS)


def from_ros_time(sec: int, nanosec: int) -> float:
    """Float seconds of a ROS time (sec, nanosec)."""
    return int(sec) + int(nanosec) / 1e9


def _to_ns(t: float) -> int:
    t = float(t)
    # A header stamp's seconds are an int32 in ROS 2 (uint32 in ROS 1): 1e300 s raised a bare
    # struct.error deep in the serialiser.
    if not (math.isfinite(t) and 0.0 <= t < 2.0**31):
        raise ValueError(f"a ROS bag time must be finite, >= 0 s and before 2038-01-19 (2**31 s), got {t!r}")
    sec = math.floor(t)
    return sec * _NS + round((t - sec) * 1e9)  # t - floor(t) is exact for floats


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def _ns_to_s(ns: int) -> float:
    sec, nanosec = divmod(ns, _NS)
    return from_ros_time(sec, nanosec)


# --- messages ------------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _ros2_store() -> Any:
    return get_typestore(Stores.ROS2_HUMBLE)


@lru_cache(maxsize=1)
def _ros1_store() -> Any:
    store = get_typestore(Stores.ROS1_NOETIC)
    # rosbags' Noetic store lacks tf2_msgs; this is its definition (md5 94810edd…, as in ROS).
    store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
    return store


def _serialize(store: Any, msg: Any, msgtype: str, ros1: bool) -> Any:
    return store.serialize_ros1(msg, msgtype) if ros1 else store.serialize_cdr(msg, msgtype)


def _header(store: Any, ns: int, frame_id: str, *, ros1: bool = False) -> Any:
    sec, nanosec = divmod(ns, _NS)
    stamp = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    header_cls = store.types["std_msgs/msg/Header"]
    if ros1:
        return header_cls(seq=0, stamp=stamp, frame_id=frame_id)
    return header_cls(stamp=stamp, frame_id=frame_id)


def _odometry_msg(
    store: Any, ns: int, pose: np.ndarray, frame_id: str, child_frame_id: str, *, ros1: bool
) -> Any:
    types = store.types
    qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(pose[2]))
    zero = types["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    return types[ODOMETRY](
        header=_header(store, ns, frame_id, ros1=ros1),
        child_frame_id=child_frame_id,
        pose=types["geometry_msgs/msg/PoseWithCovariance"](
            pose=types["geometry_msgs/msg/Pose"](
                position=types["geometry_msgs/msg/Point"](
                    x=float(pose[0]), y=float(pose[1]), z=0.0
                ),
                orientation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
            ),
            covariance=np.zeros(36),
        ),
        twist=types["geometry_msgs/msg/TwistWithCovariance"](
            twist=types["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
            covariance=np.zeros(36),
        ),
    )


def _tf_msg(
    store: Any, ns: int, pose: np.ndarray, frame_id: str, child_frame_id: str, *, ros1: bool
) -> Any:
    """A tf2_msgs/TFMessage of one planar transform frame_id → child_frame_id (x, y, yaw)."""
    types = store.types
    qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(pose[2]))
    transform = types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, ns, frame_id, ros1=ros1),
        child_frame_id=child_frame_id,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](x=float(pose[0]), y=float(pose[1]), z=0.0),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return types[TF_MESSAGE](transforms=[transform])


class _PoseStream:
    """Writes a trajectory's messages in time order, interleaved with other topics: Odometry
    messages, or with `as_tf` the transform frame_id → child_frame_id as tf2_msgs/TFMessage (as
    robots that publish their odometry only on /tf record it)."""

    def __init__(
        self, writer: Any, connection: Any, store: Any, trajectory: Trajectory,
        frame_id: str, child_frame_id: str, *, ros1: bool, as_tf: bool = False,
    ) -> None:  # fmt: skip
        self.writer, self.connection, self.store = writer, connection, store
        self.stamps = [_to_ns(t) for t in trajectory.timestamps]
        self.poses = trajectory.poses
        self.frame_id, self.child_frame_id, self.ros1 = frame_id, child_frame_id, ros1
        self.make, self.msgtype = (_tf_msg, TF_MESSAGE) if as_tf else (_odometry_msg, ODOMETRY)
        self.next = 0

    def write_until(self, ns: int | None) -> None:
        """Write every pose stamped at or before `ns` (all that remain for None)."""
        while self.next < len(self.stamps) and (ns is None or self.stamps[self.next] <= ns):
            stamp = self.stamps[self.next]
            msg = self.make(
                self.store, stamp, self.poses[self.next], self.frame_id, self.child_frame_id,
                ros1=self.ros1,
            )  # fmt: skip
            data = _serialize(self.store, msg, self.msgtype, self.ros1)
            self.writer.write(self.connection, stamp, data)
            self.next += 1


# --- reading helpers -----------------------------------------------------------------------


def bag_message_types(path: str | Path) -> set[str]:
    """The message types (e.g. "sensor_msgs/msg/Image") of every topic in a bag; InputError
    if it is not a readable bag. For telling a ToF bag from a LaserScan bag."""
    path = Path(path)
    with _opened(path) as reader:
        return {c.msgtype for c in reader.connections}


@contextmanager
def _opened(path: Path) -> Iterator[AnyReader]:
    """An open AnyReader on `path`; anything that is not a readable bag is an InputError."""
    if not path.exists():
        raise InputError("no such bag (expected a ROS 1 .bag file or a ROS 2 bag folder)", path)
    try:
        reader = AnyReader([path], default_typestore=_ros2_store())
        reader.open()
    except Exception as err:  # rosbags raises several kinds; all mean "not a readable bag"
        why = " ".join(str(err).split())  # one line: a YAML error's text spans several
        if len(why) > 200:
            why = why[:200] + "..."
        raise InputError(
            f"not a readable ROS bag ({why}); a ROS 1 bag is a file ending in '.bag', a ROS 2 "
            "bag a folder with metadata.yaml (or a bare .mcap / .db3 file)",
            path,
        ) from None
    # rosbags takes a ROS 2 bag's metadata.yaml as it is: a topic, type or count that is not
    # what its field should be would only fail later, deep in our code.
    if not all(isinstance(c.topic, str) and isinstance(c.msgtype, str)
               and isinstance(c.msgcount, int) for c in reader.connections):  # fmt: skip
        with suppress(Exception):
            reader.close()
        raise InputError(
            "not a readable ROS bag: its metadata lists a topic, message type or message count "
            "that is not one", path,
        )
    try:
        yield reader
    finally:
        with suppress(Exception):
            reader.close()


def _messages(
    reader: AnyReader, path: Path, connections: Sequence[Any]
) -> Iterator[tuple[Any, Any]]:
    """(connection, deserialised message) of `connections` in bag order; errors name the bag."""
    if not connections:
        return
    stream = reader.messages(connections=connections)
    while True:
        try:
            conn, _, raw = next(stream)
        except StopIteration:
            return
        except Exception as err:
            raise InputError(f"cannot read the bag's messages: {err}", path) from err
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as err:
            raise InputError(
                f"topic {conn.topic}: cannot decode a {conn.msgtype} message: {err}", path
            ) from err
        yield conn, msg


def _topic_listing(reader: AnyReader) -> str:
    items = sorted({(c.topic, c.msgtype) for c in reader.connections})
    text = ", ".join(f"{t} ({m})" for t, m in items[:_LISTED_TOPICS])
    if len(items) > _LISTED_TOPICS:
        text += f", … ({len(items) - _LISTED_TOPICS} more)"
    return text or "no topics at all"


def _connections(
    reader: AnyReader, path: Path, topic: str, msgtype: str | tuple[str, ...], *, required: bool = True
) -> list[Any] | None:
    """The connections of `topic`, checked to carry `msgtype` (or one of several, all alike);
    None if absent and optional."""
    types = (msgtype,) if isinstance(msgtype, str) else msgtype
    wanted = " or ".join(types)
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        if required:
            raise InputError(
                f"topic {topic} ({wanted}) is missing; the bag has: {_topic_listing(reader)}",
                path,
            )
        return None
    kinds = sorted({c.msgtype for c in conns})
    if len(kinds) > 1 or kinds[0] not in types:
        raise InputError(f"topic {topic} has type {', '.join(kinds)}, expected {wanted}", path)
    return conns


def _pick_topic(
    reader: AnyReader, path: Path, msgtype: str | tuple[str, ...], topic: str | None, conventional: str,
    choose: str, *, exclude: Iterable[str] = (),
) -> list[Any]:  # fmt: skip
    """The connections of `topic`, or of the one topic of type `msgtype` (or one of several)
    when topic is None."""
    if topic is not None:
        conns = _connections(reader, path, topic, msgtype)
        assert conns is not None  # required topics are never None
        return conns
    types = (msgtype,) if isinstance(msgtype, str) else msgtype
    wanted = " or ".join(types)
    candidates = sorted(
        {c.topic for c in reader.connections if c.msgtype in types} - set(exclude)
    )
    if len(candidates) > 1 and conventional in candidates:
        candidates = [conventional]
    if not candidates:
        raise InputError(
            f"no {wanted} topic; the bag has: {_topic_listing(reader)}", path
        )
    if len(candidates) > 1:
        raise InputError(
            f"several {wanted} topics: {', '.join(candidates)}; choose one with {choose}",
            path,
        )
    return [c for c in reader.connections if c.topic == candidates[0]]


def parse_roles(cls: Any, text: str, example: str) -> Any:
    """An instance of the dataclass `cls` from "ROLE=VALUE,ROLE=VALUE" (the roles are its
    fields; the others keep their defaults), as `--tof-topics` and `--laser-topics` take them;
    ValueError naming a bad item."""
    given: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in str(text).split(","))):
        role, eq, value = item.partition("=")
        role, value = role.strip(), value.strip()
        if not eq or not value:
            raise ValueError(f"{item!r}: expected ROLE=VALUE, e.g. {example}")
        if role not in cls.__dataclass_fields__:
            raise ValueError(f"{item!r}: unknown role {role!r}; the roles are {', '.join(cls.__dataclass_fields__)}")
        if role in given:
            raise ValueError(f"{item!r}: the role {role} is given twice")
        given[role] = value
    return cls(**given)


class _Trajectories(dict):
    """Trajectory per topic, plus the child_frame_id each topic's first message named."""

    child_frames: dict[str, str]


def _read_trajectories(
    reader: AnyReader, path: Path, connections: Sequence[Any]
) -> _Trajectories:
    """nav_msgs/Odometry messages → one Trajectory per topic (header stamps must not decrease)."""
    stamps: dict[str, list[int]] = {}
    poses: dict[str, list[tuple[float, float, float]]] = {}
    result = _Trajectories()
    result.child_frames = {}
    for conn, msg in _messages(reader, path, connections):
        topic = conn.topic
        ns = _stamp_ns(msg.header.stamp)
        previous = stamps.setdefault(topic, [])
        if previous and ns < previous[-1]:
            raise InputError(
                f"topic {topic}: timestamps go backwards: a pose stamped {_ns_to_s(ns):.9f} s "
                f"follows one stamped {_ns_to_s(previous[-1]):.9f} s",
                path,
            )
        previous.append(ns)
        pose = _planar_pose(msg.pose.pose.position, msg.pose.pose.orientation,
                            f"topic {topic}: the pose stamped {_ns_to_s(ns):.9f} s", path)
        poses.setdefault(topic, []).append(pose)
        result.child_frames.setdefault(topic, _frame_name(msg.child_frame_id))
    for conn in connections:
        if conn.topic not in stamps:
            raise InputError(f"topic {conn.topic}: has no message", path)
    for topic, ns_list in stamps.items():
        result[topic] = Trajectory(
            np.array([_ns_to_s(ns) for ns in ns_list], dtype=np.float64),
            np.array(poses[topic], dtype=np.float64),
        )
    return result


def _planar_pose(position: Any, orientation: Any, what: str, path: Path) -> tuple[float, float, float]:
    """(x, y, heading) of a message's position and quaternion (of any length, huge components
    too); an InputError naming `what` where they are not finite or the quaternion is zero."""
    p, q = position, orientation
    quaternion = np.array([q.x, q.y, q.z, q.w], dtype=np.float64)
    values = f"(position {p.x}, {p.y}, orientation {q.x}, {q.y}, {q.z}, {q.w})"
    if not (np.isfinite([p.x, p.y]).all() and np.isfinite(quaternion).all()):
        raise InputError(f"{what} is not finite {values}", path)
    if not quaternion.any():  # finite, but of length 0: no rotation, so no heading
        raise InputError(f"{what} has a zero quaternion (length 0), which gives no heading {values}", path)
    return float(p.x), float(p.y), float(quaternion_to_yaw(quaternion))


def _frame_name(frame_id: str) -> str:
    return str(frame_id).lstrip("/")  # ROS 1 tf frames may carry a leading slash


# --- sidecar, storage, atomic writing ------------------------------------------------------


def sidecar_path(path: Path) -> Path:
    """Where a bag's sidecar lies: inside a bag folder, beside a single-file (ROS 1) bag."""
    return path / SIDECAR_NAME if path.is_dir() else path.with_name(path.name + "." + SIDECAR_NAME)


def _read_sidecar(path: Path) -> dict | None:
    sidecar = sidecar_path(path)
    if not sidecar.is_file():
        return None
    try:
        data = load_yaml(sidecar.read_text(encoding="utf-8"))
    except yaml.YAMLError as err:
        problem, line = yaml_problem(err)
        raise InputError(f"the bag's sidecar is {problem}", sidecar, line) from None
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(f"cannot read the bag's sidecar: {read_problem(err)}", sidecar) from None
    if data is None:
        raise InputError("the bag's sidecar is empty: it should hold the simulated rig (omnitof simulate writes it); "
                         "remove the empty file", sidecar)
    if not isinstance(data, dict):
        raise InputError(
            f"the sidecar must hold a mapping, got a {type(data).__name__}", sidecar
        )
    version = data.get("omnitof_sidecar", SIDECAR_VERSION)
    if isinstance(version, bool) or not isinstance(version, int) or version > SIDECAR_VERSION:
        raise InputError(f"omnitof_sidecar: {version!r}: this omnitof reads sidecars of version "
                         f"{SIDECAR_VERSION} or older (written by a newer omnitof?)", sidecar)
    return data


def _sidecar_text(sidecar: dict) -> str:
    if not isinstance(sidecar, dict):
        raise ValueError(f"sidecar must be a dict, got {type(sidecar).__name__}")
    try:
        body = dump_yaml(to_plain(sidecar), sort_keys=False, allow_unicode=True)
    except yaml.YAMLError as err:
        raise ValueError(f"sidecar is not YAML-serialisable: {err}") from None
    return (
        "# omnitof sidecar of the ROS 2 bag in this folder (omnitof.io.rosbag): the data the\n"
        "# bag's messages cannot carry. Metres, radians, seconds.\n" + body
    )


def _check_written_poses(poses: np.ndarray, what: str) -> None:
    """ValueError naming the first of `poses` (N, 3) that a reader would not get back: one that
    is not finite, or whose heading its quaternion cannot hold (`geometry.check_headings`)."""
    i = first_non_finite(poses)
    if i is not None:
        raise ValueError(f"{what} pose {i} is not finite: {poses[i].tolist()}")
    check_headings(poses, what)


def _distinct_topics(roles: dict[str, str]) -> None:
    """ValueError naming two roles given one topic: a bag's reader takes a topic for one role
    (by name or type), so it would read the other role's messages as its own."""
    seen: dict[str, str] = {}
    for role, topic in roles.items():
        if topic in seen:
            raise ValueError(f"{seen[topic]} and {role} are both {topic!r}: each needs a topic of its own")
        seen[topic] = role


def _storage_plugin(storage: str) -> StoragePlugin:
    names = {"sqlite3": "SQLITE3", "mcap": "MCAP"}
    if storage not in names or not hasattr(StoragePlugin, names[storage]):
        available = [s for s, n in names.items() if hasattr(StoragePlugin, n)]
        raise ValueError(f"storage must be one of {available}, got {storage!r}")
    return getattr(StoragePlugin, names[storage])


def _fsync_tree(path: Path) -> None:
    """fsync every file under `path` (or the file itself) and the folders holding them."""
    paths = [path] if path.is_file() else [*sorted(path.rglob("*")), path]
    for p in paths:
        if p.is_file():
            with open(p, "rb") as handle:
                os.fsync(handle.fileno())
    for folder in {p if p.is_dir() else p.parent for p in paths}:
        fsync_dir(folder)


# What a ROS 2 bag folder holds: its metadata, its storage files and omnitof's sidecar.
_BAG_FOLDER_FILES = ("metadata.yaml", SIDECAR_NAME)
_BAG_STORAGE_SUFFIXES = (".mcap", ".db3", ".db3-shm", ".db3-wal")


def checked_bag_target(path: str | Path, overwrite: bool) -> Path:
    """The absolute path a bag may be written to as `path`, or an OutputError saying why not.

    It may not exist, or, with `overwrite`, be a bag: a ROS 1 bag file (.bag) or a ROS 2 bag folder
    (metadata.yaml, storage files, the sidecar). Anything else is refused even with `overwrite`,
    since the writer replaces its target as a whole: a results folder or a folder of the
    user's own would be lost. The root and the current folder (or one that holds it) are
    refused too (`omnitof.io.atomic.replaceable_place`)."""
    shown = Path(path)
    path = replaceable_place(shown, "a bag")
    if not os.path.lexists(path):
        return path
    if not overwrite:
        raise BagExistsError(f"{shown} exists already; replace it with --overwrite (overwrite=True in Python)")
    if path.is_dir():
        names = sorted(p.name for p in path.iterdir())
        foreign = [n for n in names if n not in _BAG_FOLDER_FILES and not n.endswith(_BAG_STORAGE_SUFFIXES)]
        if foreign or "metadata.yaml" not in names:
            held = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
            why = f"it holds {held}" if foreign else "it has no metadata.yaml"
            raise OutputError(f"{shown}: is a folder but not a ROS 2 bag ({why}); --overwrite replaces a bag only, "
                              "as a whole: give a new name")
    elif path.suffix != ".bag":
        raise OutputError(f"{shown}: is a file but not a ROS 1 bag (.bag); --overwrite replaces a bag only: give a new name")
    check_replaceable(path, shown, BAG)  # else the finished bag could not take its place
    return path


@contextmanager
def _atomic_path(path: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a not-yet-existing path to build a bag (file or folder) at; rename it to `path`.

    The bag is built as `.<name>.<pid>-<random>.tmp/<name>` beside `path` (its inner name is the
    final one, so a ROS 2 bag's storage file is called `<name>.mcap`; omnitof.io.atomic), synced
    to disk, and renamed into place only if the block succeeds; otherwise the staging folder is
    removed and `path` is left as it was. What a killed writer left is swept first.
    """
    path = checked_bag_target(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    with temporary_folder(path) as staging:
        inner = staging / path.name
        yield inner
        _fsync_tree(inner)
        old = staging / ".replaced"
        with deferred_signals():  # the two renames happen together or not at all
            had_old = path.exists() or path.is_symlink()
            if had_old:
                os.replace(path, old)
            try:
                os.replace(inner, path)
            except BaseException:
                if had_old:
                    os.replace(old, path)
                raise
        fsync_dir(path.parent)
