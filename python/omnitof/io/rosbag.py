"""ROS 1 and ROS 2 bags: ToF sequences (images, camera info, odometry) and planar laser scans.

Everything goes through `rosbags` (pure Python; no ROS installation is needed). Two kinds of bag:

**ToF bags** (`write_tof_bag`, `read_tof_bag`): a ROS 2 bag folder, MCAP storage by default
(`DEFAULT_STORAGE`; "sqlite3" on request), rosbag2 metadata version 8, message definitions from
ROS 2 Humble (identical in later distributions for the types used here). Default topics
(`ToFTopics`):

    /tof/distance     sensor_msgs/Image       32FC1, metres: the camera's one-way radial distance
                                              (what the ToF measures), not the depth z
    /tof/amplitude    sensor_msgs/Image       32FC1, the amplitude A of paper eq. 3, sample units
    /tof/samples      sensor_msgs/Image       32FC4, optional: the raw samples, interleaved per
                                              pixel, channel k = A_k (one topic, not four)
    /tof/camera_info  sensor_msgs/CameraInfo  one per frame: width, height, K, R = I, P = [K|0],
                                              D "plumb_bob" (k1, k2, p1, p2, k3): OpenCV's order
    /odom             nav_msgs/Odometry       odom → base_link, at the trajectory's own timestamps
    /ground_truth     nav_msgs/Odometry       world → base_link, optional (simulation)

The images and the camera info of one frame share one header stamp: that stamp *is* the frame's
timestamp, and the reader groups a frame's images by it. Each message's bag (log) time equals its
header stamp. Images are little-endian, rows packed (step = width · 4 · channels), pixel
[row, col] as in omnitof.camera. Odometry poses are planar: position (x, y, 0), orientation the
quaternion of a rotation by θ about +z, covariances and twist left zero (unknown).

The sidecar YAML (true mirror geometry, camera, world name: whatever dict the caller gives) is
stored *inside* the bag folder as `<bag>/omnitof.yaml` (`SIDECAR_NAME`), so that it travels with
the bag and is written by the same final rename; ROS 2 tools ignore files they do not list in
metadata.yaml. A bag given as a single file (a ROS 1 `.bag`, a bare `.mcap`) has its sidecar
beside it as `<file>.omnitof.yaml`.

**Laser-scan bags** (`read_laserscan_bag`, `write_laserscan_bag`): ROS 1 (`.bag` files) or ROS 2
bags with sensor_msgs/LaserScan and nav_msgs/Odometry, read into a ScanSequence.

Writing is all-or-nothing: a bag is written under a hidden temporary name beside its target
(`.<name>.<random>.tmp/`) and renamed into place only when complete, so an interrupted write
leaves no valid-looking bag. Times are ROS times (sec, nanosec) made from float seconds with
`to_ros_time` (nearest nanosecond) and read back with `from_ros_time`; they must be >= 0.
Units and frames follow omnitof.types: metres, radians, seconds; θ counter-clockwise from +x;
a range of +inf means no echo.
"""

from __future__ import annotations

import math
import os
import secrets
import shutil
import warnings
from collections import OrderedDict
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from omnitof.camera import Camera, CameraParameterError
from omnitof.errors import InputError, OmnitofError
from omnitof.geometry import interpolate_poses, quaternion_to_yaw, wrap_angle, yaw_to_quaternion
from omnitof.io.plain import to_plain
from omnitof.types import ScanSequence, Trajectory

__all__ = [
    "DEFAULT_STORAGE",
    "SIDECAR_NAME",
    "BagExistsError",
    "RosbagWarning",
    "ToFBag",
    "ToFFrameStamped",
    "ToFTopics",
    "from_ros_time",
    "interpolate_poses",
    "read_laserscan_bag",
    "read_tof_bag",
    "to_ros_time",
    "write_laserscan_bag",
    "write_tof_bag",
]

# rosbags writes MCAP since 0.10; fall back to sqlite3 with an older one.
DEFAULT_STORAGE = "mcap" if hasattr(StoragePlugin, "MCAP") else "sqlite3"
SIDECAR_NAME = "omnitof.yaml"

# rosbag2 metadata version 8 is read by ROS 2 Iron and later; rosbags writes 8 or 9 only.
_ROSBAG2_VERSION: Literal[8] = 8

IMAGE = "sensor_msgs/msg/Image"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
ODOMETRY = "nav_msgs/msg/Odometry"
LASER_SCAN = "sensor_msgs/msg/LaserScan"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"

# Frame ids written into headers (REP 105 names where there is one).
ODOM_FRAME = "odom"
WORLD_FRAME = "world"
BASE_FRAME = "base_link"
CAMERA_FRAME = "tof_optical_frame"
LASER_FRAME = "laser"

_NS = 1_000_000_000
# Images of one frame that wait for their partners; more means a topic stopped publishing.
_MAX_PENDING_FRAMES = 64
# A laser whose plane is tilted more than this is still read, with a warning.
_MAX_LASER_TILT_RAD = math.radians(5.0)
# Beam geometry (angles in rad, range limits in m) must agree this well across scans; also the
# tolerance on evenly spaced beams when writing (LaserScan stores angle_min + i·increment).
_GEOMETRY_TOLERANCE = 1e-6
_LISTED_TOPICS = 20  # how many topics an error message lists


class BagExistsError(OmnitofError, FileExistsError):
    """The target of a bag writer exists and `overwrite` was not given."""


class RosbagWarning(UserWarning):
    """Data read from a bag were usable but not as expected (dropped scans, no laser pose)."""


# --- plain types ---------------------------------------------------------------------------


@dataclass
class ToFFrameStamped:
    """One ToF camera frame with its time.

    Attributes:
        timestamp: seconds (ROS time), the header stamp of the frame's images.
        distance: (H, W) float32, metres, one-way radial distance per pixel.
        amplitude: (H, W) float32, sample units.
        samples: (4, H, W) float32 raw samples A0..A3, or None.
        odometry: (3,) float64 odometry pose (x, y, θ) at `timestamp`, interpolated by
            `ToFBag.frames`; None outside the odometry's time span or when the bag has none.
            Ignored by `write_tof_bag`, which takes the whole trajectory.
        ground_truth: (3,) float64 true pose at `timestamp`, likewise.
    """

    timestamp: float
    distance: np.ndarray
    amplitude: np.ndarray
    samples: np.ndarray | None = None
    odometry: np.ndarray | None = None
    ground_truth: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.timestamp = float(self.timestamp)
        self.distance = np.asarray(self.distance, dtype=np.float32)
        self.amplitude = np.asarray(self.amplitude, dtype=np.float32)
        if self.distance.ndim != 2:
            raise ValueError(f"distance must be an (H, W) image, got shape {self.distance.shape}")
        if self.amplitude.shape != self.distance.shape:
            raise ValueError(
                f"amplitude must have the shape of distance {self.distance.shape}, "
                f"got {self.amplitude.shape}"
            )
        if self.samples is not None:
            self.samples = np.asarray(self.samples, dtype=np.float32)
            if self.samples.shape != (4, *self.distance.shape):
                raise ValueError(
                    f"samples must have shape (4, H, W) = {(4, *self.distance.shape)}, "
                    f"got {self.samples.shape}"
                )


@dataclass(frozen=True)
class ToFTopics:
    """Topic names of a ToF bag (the defaults are what `write_tof_bag` writes)."""

    distance: str = "/tof/distance"
    amplitude: str = "/tof/amplitude"
    samples: str = "/tof/samples"
    camera_info: str = "/tof/camera_info"
    odometry: str = "/odom"
    ground_truth: str = "/ground_truth"


# --- time and poses ------------------------------------------------------------------------


def to_ros_time(t: float) -> tuple[int, int]:
    """(sec, nanosec) of a time in float seconds, to the nearest nanosecond; t must be >= 0.

    The whole seconds are split off exactly before rounding, so epoch times (~1.7e9 s) keep the
    full precision of their float.
    """
    return divmod(_to_ns(t), _NS)


def from_ros_time(sec: int, nanosec: int) -> float:
    """Float seconds of a ROS time (sec, nanosec)."""
    return int(sec) + int(nanosec) / 1e9


def _to_ns(t: float) -> int:
    t = float(t)
    if not math.isfinite(t) or t < 0.0:
        raise ValueError(f"a ROS bag time must be finite and >= 0 s, got {t!r}")
    sec = math.floor(t)
    return sec * _NS + round((t - sec) * 1e9)  # t - floor(t) is exact for floats


def _stamp_ns(stamp: Any) -> int:
    return int(stamp.sec) * _NS + int(stamp.nanosec)


def _ns_to_s(ns: int) -> float:
    sec, nanosec = divmod(ns, _NS)
    return from_ros_time(sec, nanosec)


# --- writing ToF bags ----------------------------------------------------------------------


def write_tof_bag(
    path: str | Path,
    frames: Iterable[ToFFrameStamped],
    *,
    camera: Camera,
    odometry: Trajectory,
    ground_truth: Trajectory | None = None,
    sidecar: dict | None = None,
    storage: str = DEFAULT_STORAGE,
    topics: ToFTopics = ToFTopics(),
    overwrite: bool = False,
) -> int:
    """Write a ToF sequence as a ROS 2 bag folder (layout in the module docstring).

    `frames` is consumed one at a time, so a long sequence can be generated on the fly and
    never held in memory. Odometry and ground-truth messages are interleaved with the frames in
    time order. Raw samples are written when the first frame has them (then every frame must).

    Args:
        path: the bag folder to create (ROS 2 bags are folders; not ending in ".bag", which
            readers take for a ROS 1 bag file).
        frames: ToFFrameStamped with strictly increasing timestamps, images of camera.shape.
        camera: the intrinsics written to every camera_info message.
        odometry: odometry poses (odom → base_link) with non-decreasing timestamps.
        ground_truth: true poses (world → base_link), or None.
        sidecar: a YAML-serialisable dict (numpy arrays and scalars are converted) written to
            `<bag>/omnitof.yaml`, or None for no sidecar.
        storage: "mcap" or "sqlite3".
        topics: topic names.
        overwrite: replace an existing bag at `path` (the old one is moved aside only once the
            new one is complete, and restored if the final rename fails).

    Returns:
        The number of frames written.

    Raises:
        BagExistsError: `path` exists and overwrite is False.
        ValueError: bad frames, trajectories or arguments (nothing is left at `path`).
    """
    path = Path(path)
    plugin = _storage_plugin(storage)
    if path.suffix == ".bag":
        raise ValueError(
            f"{path}: a ROS 2 bag folder must not end in '.bag' (readers take that for ROS 1)"
        )
    odometry = _checked_trajectory(odometry, "odometry")
    if ground_truth is not None:
        ground_truth = _checked_trajectory(ground_truth, "ground_truth")
    sidecar_text = None if sidecar is None else _sidecar_text(sidecar)
    store = _ros2_store()

    count = 0
    with _atomic_path(path, overwrite) as staging:
        with Writer2(staging, version=_ROSBAG2_VERSION, storage_plugin=plugin) as writer:
            conn_distance = writer.add_connection(topics.distance, IMAGE, typestore=store)
            conn_amplitude = writer.add_connection(topics.amplitude, IMAGE, typestore=store)
            conn_info = writer.add_connection(topics.camera_info, CAMERA_INFO, typestore=store)
            conn_samples = None
            pose_streams = [
                _PoseStream(
                    writer,
                    writer.add_connection(topics.odometry, ODOMETRY, typestore=store),
                    store, odometry, ODOM_FRAME, BASE_FRAME, ros1=False,
                )
            ]  # fmt: skip
            if ground_truth is not None:
                conn_truth = writer.add_connection(topics.ground_truth, ODOMETRY, typestore=store)
                pose_streams.append(
                    _PoseStream(
                        writer, conn_truth, store, ground_truth, WORLD_FRAME, BASE_FRAME,
                        ros1=False,
                    )
                )  # fmt: skip
            has_samples = False
            previous_ns = -1
            for frame in frames:
                if not isinstance(frame, ToFFrameStamped):
                    raise ValueError(
                        f"frames must be ToFFrameStamped, got {type(frame).__name__} "
                        f"(frame {count})"
                    )
                if frame.distance.shape != camera.shape:
                    raise ValueError(
                        f"frame {count} (t = {frame.timestamp} s): image shape "
                        f"{frame.distance.shape} is not the camera's (height, width) = "
                        f"{camera.shape}"
                    )
                ns = _to_ns(frame.timestamp)
                if ns <= previous_ns:
                    raise ValueError(
                        f"frame timestamps must increase: frame {count} at {frame.timestamp} s "
                        f"follows {_ns_to_s(previous_ns)} s"
                    )
                if count == 0:
                    has_samples = frame.samples is not None
                    if has_samples:
                        conn_samples = writer.add_connection(topics.samples, IMAGE, typestore=store)
                elif (frame.samples is not None) != has_samples:
                    raise ValueError(
                        f"frame {count} (t = {frame.timestamp} s) "
                        f"{'lacks' if has_samples else 'has'} raw samples, unlike frame 0: "
                        "either every frame has them or none"
                    )
                for stream in pose_streams:
                    stream.write_until(ns)
                header = _header(store, ns, CAMERA_FRAME)
                writer.write(conn_info, ns, _camera_info_cdr(store, header, camera))
                writer.write(conn_distance, ns, _image_cdr(store, header, frame.distance, "32FC1"))
                writer.write(
                    conn_amplitude, ns, _image_cdr(store, header, frame.amplitude, "32FC1")
                )
                if conn_samples is not None and frame.samples is not None:
                    interleaved = np.moveaxis(frame.samples, 0, -1)  # (H, W, 4): A0..A3/pixel
                    writer.write(conn_samples, ns, _image_cdr(store, header, interleaved, "32FC4"))
                previous_ns = ns
                count += 1
            if count == 0:
                raise ValueError("write_tof_bag needs at least one frame")
            for stream in pose_streams:
                stream.write_until(None)
        if sidecar_text is not None:
            (staging / SIDECAR_NAME).write_text(sidecar_text, encoding="utf-8")
    return count


class _PoseStream:
    """Writes a trajectory's Odometry messages in time order, interleaved with other topics."""

    def __init__(
        self, writer: Any, connection: Any, store: Any, trajectory: Trajectory,
        frame_id: str, child_frame_id: str, *, ros1: bool,
    ) -> None:  # fmt: skip
        self.writer, self.connection, self.store = writer, connection, store
        self.stamps = [_to_ns(t) for t in trajectory.timestamps]
        self.poses = trajectory.poses
        self.frame_id, self.child_frame_id, self.ros1 = frame_id, child_frame_id, ros1
        self.next = 0

    def write_until(self, ns: int | None) -> None:
        """Write every pose stamped at or before `ns` (all that remain for None)."""
        while self.next < len(self.stamps) and (ns is None or self.stamps[self.next] <= ns):
            stamp = self.stamps[self.next]
            msg = _odometry_msg(
                self.store, stamp, self.poses[self.next], self.frame_id, self.child_frame_id,
                ros1=self.ros1,
            )  # fmt: skip
            data = _serialize(self.store, msg, ODOMETRY, self.ros1)
            self.writer.write(self.connection, stamp, data)
            self.next += 1


# --- reading ToF bags ----------------------------------------------------------------------


@dataclass
class ToFBag:
    """A ToF bag opened by `read_tof_bag`: metadata, trajectories and a streaming frame reader.

    Attributes:
        path: the bag.
        camera: intrinsics from the first camera_info message.
        odometry: the odometry poses as recorded (their own timestamps), or None when the bag
            has none and read_tof_bag was told not to require it.
        ground_truth: the ground-truth poses as recorded, or None.
        sidecar: the sidecar dict (`<bag>/omnitof.yaml`), or None when there is none.
        topics: the topic names used.
        n_frames: the number of distance images in the bag.
        has_samples: whether the bag has the raw-samples topic.
    """

    path: Path
    camera: Camera
    odometry: Trajectory | None
    ground_truth: Trajectory | None
    sidecar: dict | None
    topics: ToFTopics
    n_frames: int
    has_samples: bool
    _timestamps: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    def __len__(self) -> int:
        return self.n_frames

    def __iter__(self) -> Iterator[ToFFrameStamped]:
        return self.frames()

    def frames(self, *, samples: bool = True) -> Iterator[ToFFrameStamped]:
        """Stream the frames in time order, each with its interpolated odometry pose.

        Opens the bag anew on every call, holds only a few frames at a time, and closes it when
        the iteration ends or the iterator is dropped. A frame whose images are incomplete (one
        topic dropped that stamp) is skipped with a RosbagWarning.

        Args:
            samples: also read the raw samples when the bag has them (False saves I/O).

        Raises:
            InputError: naming the bag and topic, for a wrong encoding, an image whose size is
                not camera_info's, timestamps that go backwards, or a topic that stops.
        """
        roles = {self.topics.distance: "distance", self.topics.amplitude: "amplitude"}
        if samples and self.has_samples:
            roles[self.topics.samples] = "samples"
        formats = {"distance": ("32FC1", 1), "amplitude": ("32FC1", 1), "samples": ("32FC4", 4)}
        shape = self.camera.shape
        last_ns = dict.fromkeys(roles.values(), -1)
        pending: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        emitted_ns = -1
        dropped: list[int] = []
        with _opened(self.path) as reader:
            connections = [c for c in reader.connections if c.topic in roles]
            for conn, msg in _messages(reader, self.path, connections):
                role = roles[conn.topic]
                ns = _stamp_ns(msg.header.stamp)
                if ns <= last_ns[role]:
                    raise InputError(
                        f"topic {conn.topic}: timestamps go backwards: an image stamped "
                        f"{_ns_to_s(ns):.9f} s follows one stamped {_ns_to_s(last_ns[role]):.9f} s",
                        self.path,
                    )
                last_ns[role] = ns
                encoding, channels = formats[role]
                pending.setdefault(ns, {})[role] = _decode_image(
                    msg, self.path, conn.topic, encoding, channels, shape,
                    self.topics.camera_info,
                )  # fmt: skip
                while pending:
                    stamp, parts = next(iter(pending.items()))
                    missing = [r for r in last_ns if r not in parts]
                    if missing and not all(last_ns[r] > stamp for r in missing):
                        break  # its missing images may still come
                    del pending[stamp]
                    if missing:
                        dropped.append(stamp)
                        continue
                    if stamp <= emitted_ns:
                        raise InputError(
                            f"topic {self.topics.distance}: timestamps go backwards: the frame "
                            f"at {_ns_to_s(stamp):.9f} s completes after the frame at "
                            f"{_ns_to_s(emitted_ns):.9f} s",
                            self.path,
                        )
                    emitted_ns = stamp
                    yield self._frame(stamp, parts)
                if len(pending) > _MAX_PENDING_FRAMES:
                    stamp, parts = next(iter(pending.items()))
                    missing = [t for t, r in roles.items() if r not in parts]
                    raise InputError(
                        f"topic {', '.join(missing)}: no image for the frame at "
                        f"{_ns_to_s(stamp):.9f} s while {len(pending)} frames wait for it; "
                        "the images of one frame must share one header stamp",
                        self.path,
                    )
        dropped.extend(pending)
        if dropped:
            warnings.warn(
                f"{self.path}: skipped {len(dropped)} frame(s) whose images were incomplete "
                f"(first at {_ns_to_s(dropped[0]):.9f} s)",
                RosbagWarning,
                stacklevel=2,
            )

    def frame_timestamps(self) -> np.ndarray:
        """(N,) float64 header stamps of the distance images, seconds (one pass, cached)."""
        if self._timestamps is None:
            stamps = []
            with _opened(self.path) as reader:
                connections = [c for c in reader.connections if c.topic == self.topics.distance]
                for _, msg in _messages(reader, self.path, connections):
                    stamps.append(_stamp_ns(msg.header.stamp))
            self._timestamps = np.array([_ns_to_s(ns) for ns in stamps], dtype=np.float64)
        return self._timestamps

    def odometry_at(self, timestamps: np.ndarray | float) -> np.ndarray:
        """Odometry poses (N, 3) at `timestamps` (see interpolate_poses); NaN outside its span."""
        if self.odometry is None:
            return np.full((np.size(timestamps), 3), np.nan)
        return interpolate_poses(self.odometry, timestamps)

    def frame_odometry(self) -> Trajectory:
        """The odometry pose at every frame's timestamp, interpolated (InputError outside)."""
        return self._at_frames(self.odometry, self.topics.odometry)

    def frame_ground_truth(self) -> Trajectory | None:
        """The true pose at every frame's timestamp, interpolated; None without ground truth."""
        if self.ground_truth is None:
            return None
        return self._at_frames(self.ground_truth, self.topics.ground_truth)

    def _at_frames(self, trajectory: Trajectory | None, topic: str) -> Trajectory:
        if trajectory is None:
            raise InputError(f"topic {topic}: the bag has no odometry", self.path)
        t = self.frame_timestamps()
        poses = interpolate_poses(trajectory, t)
        outside = np.flatnonzero(np.isnan(poses[:, 0]))
        if outside.size:
            raise InputError(
                f"topic {topic}: frame {outside[0]} at {t[outside[0]]:.9f} s is outside the "
                f"poses' time span [{trajectory.timestamps[0]:.9f}, "
                f"{trajectory.timestamps[-1]:.9f}] s",
                self.path,
            )
        return Trajectory(t, poses)

    def _frame(self, ns: int, parts: dict[str, np.ndarray]) -> ToFFrameStamped:
        t = _ns_to_s(ns)
        samples = parts.get("samples")
        if samples is not None:
            samples = np.ascontiguousarray(np.moveaxis(samples, -1, 0))
        odometry = ground_truth = None
        if self.odometry is not None:
            pose = interpolate_poses(self.odometry, t)[0]
            odometry = None if np.isnan(pose[0]) else pose
        if self.ground_truth is not None:
            pose = interpolate_poses(self.ground_truth, t)[0]
            ground_truth = None if np.isnan(pose[0]) else pose
        return ToFFrameStamped(
            t, parts["distance"], parts["amplitude"], samples, odometry, ground_truth
        )


def read_tof_bag(
    path: str | Path, *, topics: ToFTopics = ToFTopics(), require_odometry: bool = True
) -> ToFBag:
    """Open a ToF bag: read its camera, trajectories and sidecar; stream frames on demand.

    Reads any ROS 1 or ROS 2 bag with the topics of `topics` (the layout of the module
    docstring). Reading the frames is left to `ToFBag.frames()`, which streams them.

    Args:
        path: a ROS 2 bag folder (or bare .mcap/.db3 file), or a ROS 1 .bag file.
        topics: topic names.
        require_odometry: when False, a bag without the odometry topic is accepted (odometry
            None), e.g. a recording of a calibration target.

    Raises:
        InputError: naming the bag (and the topic): not a bag, a missing topic or one of the
            wrong type, a camera_info omnitof's Camera cannot represent, odometry timestamps
            that go backwards, an unreadable sidecar.
    """
    path = Path(path)
    with _opened(path) as reader:
        _connections(reader, path, topics.distance, IMAGE)
        _connections(reader, path, topics.amplitude, IMAGE)
        info = _connections(reader, path, topics.camera_info, CAMERA_INFO) or []
        samples = _connections(reader, path, topics.samples, IMAGE, required=False)
        odometry = _connections(
            reader, path, topics.odometry, ODOMETRY, required=require_odometry
        )
        truth = _connections(reader, path, topics.ground_truth, ODOMETRY, required=False)
        n_frames = sum(c.msgcount for c in reader.connections if c.topic == topics.distance)
        camera = None
        for _, msg in _messages(reader, path, info):
            camera = _camera_from_info(msg, path, topics.camera_info)
            break
        if camera is None:
            raise InputError(f"topic {topics.camera_info}: has no message", path)
        trajectories = _read_trajectories(reader, path, (odometry or []) + (truth or []))
    return ToFBag(
        path=path,
        camera=camera,
        odometry=trajectories.get(topics.odometry) if odometry else None,
        ground_truth=trajectories.get(topics.ground_truth) if truth else None,
        sidecar=_read_sidecar(path),
        topics=topics,
        n_frames=n_frames,
        has_samples=samples is not None,
    )


# --- laser-scan bags -----------------------------------------------------------------------


def read_laserscan_bag(
    path: str | Path,
    *,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    ground_truth_topic: str | None = "/ground_truth",
    tf_static_topic: str = "/tf_static",
) -> ScanSequence:
    """Read sensor_msgs/LaserScan and nav_msgs/Odometry from a ROS 1 or ROS 2 bag.

    - Topics: when not given, found by type. Several candidates are ambiguous unless one is
      the conventional name ("/scan", "/odom"); the ground-truth topic is never taken for
      odometry. The error lists the candidates.
    - Ranges: NaN, ±inf and values outside [range_min, range_max] become +inf (no echo).
      Beam i is at angle_min + i·angle_increment; max_range = range_max; intensities become
      `remissions` when every scan has one per beam. Beam geometry must not change.
    - Time: each scan's header stamp; stamps must not decrease. The odometry (its header
      stamps must not decrease either) is interpolated to each scan's stamp (linear in x, y,
      shorter arc in θ); scans outside the odometry's time span are dropped with a
      RosbagWarning.
    - Ground truth: Odometry messages on `ground_truth_topic`, interpolated the same way, when
      the topic exists and covers every kept scan (else None, with a warning).
    - sensor_pose: base → laser from the static transforms on `tf_static_topic`, where base is
      the odometry's child_frame_id (default base_link) and laser the scans' frame_id, chained
      through intermediate frames and projected to the plane (x, y, yaw). An upside-down laser
      gets its angles negated. Without such a transform: zeros and a RosbagWarning.

    Raises:
        InputError: naming the bag and topic: not a bag, no or ambiguous topics, changing beam
            geometry, timestamps that go backwards, no scan within the odometry's span.
    """
    path = Path(path)
    with _opened(path) as reader:
        scan_conns = _pick_topic(reader, path, LASER_SCAN, scan_topic, "/scan", "scan_topic")
        exclude = {ground_truth_topic} if ground_truth_topic else set()
        odom_conns = _pick_topic(
            reader, path, ODOMETRY, odom_topic, "/odom", "odom_topic", exclude=exclude
        )
        # Optional topics are used only when they carry the expected type.
        truth_conns = [
            c for c in reader.connections
            if c.topic == ground_truth_topic and c.topic != odom_conns[0].topic
            and c.msgtype == ODOMETRY
        ]  # fmt: skip
        tf_conns = [
            c for c in reader.connections if c.topic == tf_static_topic and c.msgtype == TF_MESSAGE
        ]
        scan_name, odom_name = scan_conns[0].topic, odom_conns[0].topic

        trajectories = _read_trajectories(reader, path, odom_conns + truth_conns)
        base_frame = trajectories.child_frames.get(odom_name) or BASE_FRAME
        static = _read_static_transforms(reader, path, tf_conns)

        stamps: list[int] = []
        ranges: list[np.ndarray] = []
        intensities: list[np.ndarray] = []
        geometry: tuple[float, float, int, float, float] | None = None
        laser_frame = ""
        for _, msg in _messages(reader, path, scan_conns):
            ns = _stamp_ns(msg.header.stamp)
            if stamps and ns < stamps[-1]:
                raise InputError(
                    f"topic {scan_name}: timestamps go backwards: a scan stamped "
                    f"{_ns_to_s(ns):.9f} s follows one stamped {_ns_to_s(stamps[-1]):.9f} s",
                    path,
                )
            r = np.array(msg.ranges, dtype=np.float32)
            this = (
                float(msg.angle_min), float(msg.angle_increment), len(r),
                float(msg.range_min), float(msg.range_max),
            )  # fmt: skip
            if geometry is None:
                geometry, laser_frame = this, _frame_name(msg.header.frame_id)
                if not (math.isfinite(this[4]) and this[4] > 0.0):
                    raise InputError(
                        f"topic {scan_name}: range_max must be a positive number, got {this[4]}",
                        path,
                    )
            elif this[2] != geometry[2] or not np.allclose(
                this, geometry, rtol=0.0, atol=_GEOMETRY_TOLERANCE
            ):
                raise InputError(
                    f"topic {scan_name}: the scan at {_ns_to_s(ns):.9f} s has beam geometry "
                    f"(angle_min, angle_increment, beams, range_min, range_max) = {this}, "
                    f"the first had {geometry}; one ScanSequence needs one geometry",
                    path,
                )
            with np.errstate(invalid="ignore"):
                valid = (r >= geometry[3]) & (r <= geometry[4])  # False for NaN
            r[~valid] = np.inf
            stamps.append(ns)
            ranges.append(r)
            intensities.append(np.asarray(msg.intensities, dtype=np.float32))
    if geometry is None:
        raise InputError(f"topic {scan_name}: has no message", path)

    angle_min, increment, n_beams, _, range_max = geometry
    angles = angle_min + increment * np.arange(n_beams, dtype=np.float64)
    t = np.array([_ns_to_s(ns) for ns in stamps], dtype=np.float64)
    odometry = trajectories[odom_name]
    poses = interpolate_poses(odometry, t)
    keep = ~np.isnan(poses[:, 0])
    if not keep.any():
        raise InputError(
            f"topic {odom_name}: no scan on {scan_name} lies within the odometry's time span "
            f"{_span(odometry)}",
            path,
        )
    if not keep.all():
        warnings.warn(
            f"{path}: dropped {int((~keep).sum())} of {len(t)} scans on {scan_name} that lie "
            f"outside the odometry's time span {_span(odometry)} (topic {odom_name})",
            RosbagWarning,
            stacklevel=2,
        )
    ground_truth = None
    if truth_conns:
        truth = trajectories[truth_conns[0].topic]
        ground_truth = interpolate_poses(truth, t[keep])
        if np.isnan(ground_truth[:, 0]).any():
            warnings.warn(
                f"{path}: topic {ground_truth_topic} does not cover every scan "
                f"(its span is {_span(truth)}); ground truth left out",
                RosbagWarning,
                stacklevel=2,
            )
            ground_truth = None

    scan_ranges = np.stack(ranges)[keep]
    remissions = None
    if all(len(i) == n_beams for i in intensities):
        remissions = np.stack(intensities)[keep]
    sensor_pose, flipped = _laser_pose(static, base_frame, laser_frame, path, tf_static_topic)
    if flipped:
        angles = -angles
    return ScanSequence(
        timestamps=t[keep],
        ranges=scan_ranges,
        angles=angles,
        odometry=poses[keep],
        sensor_pose=sensor_pose,
        max_range=range_max,
        remissions=remissions,
        ground_truth=ground_truth,
        source=str(path),
    )


def write_laserscan_bag(
    path: str | Path,
    scans: ScanSequence,
    *,
    version: int = 2,
    storage: str = DEFAULT_STORAGE,
    scan_topic: str = "/scan",
    odom_topic: str = "/odom",
    ground_truth_topic: str = "/ground_truth",
    tf_static_topic: str = "/tf_static",
    overwrite: bool = False,
) -> None:
    """Write a ScanSequence as a ROS 1 (version=1) or ROS 2 (version=2) bag.

    Per scan, in time order: the odometry pose (nav_msgs/Odometry odom → base_link), the ground
    truth when the sequence has it (world → base_link), and the scan (sensor_msgs/LaserScan in
    frame "laser", range_min 0, range_max = max_range, +inf kept for no echo, intensities from
    remissions), all with the scan's stamp. One static transform base_link → laser from
    sensor_pose on /tf_static (latched in ROS 1). Readings beyond max_range stay in the bag as
    they are; readers (this one too) take them for no echo.

    Args:
        path: a ".bag" file for version 1 (ROS 1 readers recognise bags by it); a folder not
            ending in ".bag" for version 2.
        scans: evenly spaced beams (LaserScan stores angle_min + i·angle_increment, in
            float32), timestamps non-decreasing and >= 0.
        storage: ROS 2 storage, "mcap" or "sqlite3".
        overwrite: replace an existing bag at `path`.

    Raises:
        BagExistsError: `path` exists and overwrite is False.
        ValueError: uneven beams, timestamps going backwards, a bad path or version.
    """
    path = Path(path)
    if version not in (1, 2):
        raise ValueError(f"version must be 1 (ROS 1) or 2 (ROS 2), got {version!r}")
    if version == 1 and path.suffix != ".bag":
        raise ValueError(f"{path}: a ROS 1 bag must end in '.bag' (readers recognise it so)")
    if version == 2 and path.suffix == ".bag":
        raise ValueError(
            f"{path}: a ROS 2 bag folder must not end in '.bag' (readers take that for ROS 1)"
        )
    plugin = _storage_plugin(storage)
    angle_min, increment = _even_beams(scans.angles)
    stamps = [_to_ns(t) for t in scans.timestamps]
    if any(b < a for a, b in zip(stamps, stamps[1:])):
        raise ValueError("write_laserscan_bag: scan timestamps must not decrease")
    if not len(scans):
        raise ValueError("write_laserscan_bag needs at least one scan")
    if not (math.isfinite(scans.max_range) and scans.max_range > 0.0):
        raise ValueError(f"max_range must be a positive number, got {scans.max_range}")
    ros1 = version == 1
    store = _ros1_store() if ros1 else _ros2_store()
    intensities = (
        scans.remissions if scans.remissions is not None else np.zeros((len(scans), 0), np.float32)
    )

    with _atomic_path(path, overwrite) as staging:
        writer: Any = (
            Writer1(staging)
            if ros1
            else Writer2(staging, version=_ROSBAG2_VERSION, storage_plugin=plugin)
        )
        with writer:
            add = _adder(writer, store, ros1)
            conn_tf = add(tf_static_topic, TF_MESSAGE, latching=True)
            conn_scan = add(scan_topic, LASER_SCAN)
            conn_odom = add(odom_topic, ODOMETRY)
            streams = [
                _PoseStream(
                    writer, conn_odom, store, Trajectory(scans.timestamps, scans.odometry),
                    ODOM_FRAME, BASE_FRAME, ros1=ros1,
                )
            ]  # fmt: skip
            if scans.ground_truth is not None:
                conn_truth = add(ground_truth_topic, ODOMETRY)
                streams.append(
                    _PoseStream(
                        writer, conn_truth, store,
                        Trajectory(scans.timestamps, scans.ground_truth),
                        WORLD_FRAME, BASE_FRAME, ros1=ros1,
                    )
                )  # fmt: skip
            tf = _tf_static_msg(store, stamps[0], scans.sensor_pose, ros1=ros1)
            writer.write(conn_tf, stamps[0], _serialize(store, tf, TF_MESSAGE, ros1))
            scan_cls = store.types[LASER_SCAN]
            for k, ns in enumerate(stamps):
                for stream in streams:
                    stream.write_until(ns)
                msg = scan_cls(
                    header=_header(store, ns, LASER_FRAME, ros1=ros1),
                    angle_min=angle_min,
                    angle_max=angle_min + increment * (scans.n_beams - 1),
                    angle_increment=increment,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.0,
                    range_max=float(scans.max_range),
                    ranges=np.ascontiguousarray(scans.ranges[k], dtype=np.float32),
                    intensities=np.ascontiguousarray(intensities[k], dtype=np.float32),
                )
                writer.write(conn_scan, ns, _serialize(store, msg, LASER_SCAN, ros1))


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


def _adder(writer: Any, store: Any, ros1: bool) -> Any:
    def add(topic: str, msgtype: str, *, latching: bool = False) -> Any:
        if ros1:
            return writer.add_connection(
                topic, msgtype, typestore=store, latching=1 if latching else None
            )
        return writer.add_connection(topic, msgtype, typestore=store)

    return add


def _header(store: Any, ns: int, frame_id: str, *, ros1: bool = False) -> Any:
    sec, nanosec = divmod(ns, _NS)
    stamp = store.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec)
    header_cls = store.types["std_msgs/msg/Header"]
    if ros1:
        return header_cls(seq=0, stamp=stamp, frame_id=frame_id)
    return header_cls(stamp=stamp, frame_id=frame_id)


def _image_cdr(store: Any, header: Any, image: np.ndarray, encoding: str) -> Any:
    data = np.ascontiguousarray(image, dtype="<f4")
    height, width = data.shape[:2]
    channels = 1 if data.ndim == 2 else data.shape[2]
    msg = store.types[IMAGE](
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * 4 * channels,
        data=data.reshape(-1).view(np.uint8),
    )
    return store.serialize_cdr(msg, IMAGE)


def _camera_info_cdr(store: Any, header: Any, camera: Camera) -> Any:
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx, camera.cy
    roi = store.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
    )
    msg = store.types[CAMERA_INFO](
        header=header,
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=np.array(camera.dist, dtype=np.float64),
        k=camera.K.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=np.array([fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0]),
        binning_x=0,
        binning_y=0,
        roi=roi,
    )
    return store.serialize_cdr(msg, CAMERA_INFO)


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


def _tf_static_msg(store: Any, ns: int, sensor_pose: np.ndarray, *, ros1: bool) -> Any:
    types = store.types
    qx, qy, qz, qw = (float(v) for v in yaw_to_quaternion(sensor_pose[2]))
    transform = types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, ns, BASE_FRAME, ros1=ros1),
        child_frame_id=LASER_FRAME,
        transform=types["geometry_msgs/msg/Transform"](
            translation=types["geometry_msgs/msg/Vector3"](
                x=float(sensor_pose[0]), y=float(sensor_pose[1]), z=0.0
            ),
            rotation=types["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
        ),
    )
    return types[TF_MESSAGE](transforms=[transform])


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
        raise InputError(
            f"not a readable ROS bag ({err}); a ROS 1 bag is a file ending in '.bag', a ROS 2 "
            "bag a folder with metadata.yaml (or a bare .mcap / .db3 file)",
            path,
        ) from None
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
    reader: AnyReader, path: Path, topic: str, msgtype: str, *, required: bool = True
) -> list[Any] | None:
    """The connections of `topic`, checked to carry `msgtype`; None if absent and optional."""
    conns = [c for c in reader.connections if c.topic == topic]
    if not conns:
        if required:
            raise InputError(
                f"topic {topic} ({msgtype}) is missing; the bag has: {_topic_listing(reader)}",
                path,
            )
        return None
    wrong = sorted({c.msgtype for c in conns if c.msgtype != msgtype})
    if wrong:
        raise InputError(f"topic {topic} has type {', '.join(wrong)}, expected {msgtype}", path)
    return conns


def _pick_topic(
    reader: AnyReader, path: Path, msgtype: str, topic: str | None, conventional: str,
    argument: str, *, exclude: Iterable[str] = (),
) -> list[Any]:  # fmt: skip
    """The connections of `topic`, or of the one topic of type `msgtype` when topic is None."""
    if topic is not None:
        conns = _connections(reader, path, topic, msgtype)
        assert conns is not None  # required topics are never None
        return conns
    candidates = sorted(
        {c.topic for c in reader.connections if c.msgtype == msgtype} - set(exclude)
    )
    if len(candidates) > 1 and conventional in candidates:
        candidates = [conventional]
    if not candidates:
        raise InputError(
            f"no {msgtype} topic; the bag has: {_topic_listing(reader)}", path
        )
    if len(candidates) > 1:
        raise InputError(
            f"several {msgtype} topics: {', '.join(candidates)}; choose one with {argument}=",
            path,
        )
    return [c for c in reader.connections if c.topic == candidates[0]]


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
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        yaw = float(quaternion_to_yaw(np.array([q.x, q.y, q.z, q.w])))
        poses.setdefault(topic, []).append((float(p.x), float(p.y), yaw))
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


def _decode_image(
    msg: Any, path: Path, topic: str, encoding: str, channels: int,
    shape: tuple[int, int], info_topic: str,
) -> np.ndarray:  # fmt: skip
    """(H, W) or (H, W, channels) float32 pixels of a sensor_msgs/Image, checked."""
    if msg.encoding != encoding:
        raise InputError(
            f"topic {topic}: image encoding {msg.encoding!r}, expected {encoding!r}", path
        )
    height, width = int(msg.height), int(msg.width)
    if (height, width) != shape:
        raise InputError(
            f"topic {topic}: image of {width}×{height} pixels at "
            f"{_ns_to_s(_stamp_ns(msg.header.stamp)):.9f} s, but {info_topic} says "
            f"{shape[1]}×{shape[0]}",
            path,
        )
    row = width * 4 * channels
    data = np.asarray(msg.data, dtype=np.uint8)
    if msg.step < row or data.size != msg.step * height:
        raise InputError(
            f"topic {topic}: image step {msg.step} and {data.size} data bytes do not fit "
            f"{width}×{height} {encoding} pixels",
            path,
        )
    rows = data.reshape(height, msg.step)[:, :row].copy()  # copy: detach from the bag's buffer
    pixels = rows.view(">f4" if msg.is_bigendian else "<f4").astype(np.float32, copy=False)
    return pixels.reshape((height, width) if channels == 1 else (height, width, channels))


def _camera_from_info(msg: Any, path: Path, topic: str) -> Camera:
    """omnitof's Camera from a sensor_msgs/CameraInfo (plumb_bob, no skew)."""
    k = np.asarray(msg.k, dtype=np.float64)
    d = [float(v) for v in msg.d]
    model = str(msg.distortion_model)
    if model in ("plumb_bob", "rational_polynomial") and len(d) in (5, 8):
        if any(d[5:]):
            raise InputError(
                f"topic {topic}: rational_polynomial coefficients k4..k6 = {d[5:]} are not "
                "supported (omnitof's Camera has k1, k2, p1, p2, k3)",
                path,
            )
        dist = tuple(d[:5])
    elif len(d) == 0 or not any(d):
        dist = (0.0,) * 5
    else:
        raise InputError(
            f"topic {topic}: distortion model {model!r} with {len(d)} coefficients is not "
            "supported; expected plumb_bob (k1, k2, p1, p2, k3)",
            path,
        )
    if k[1] != 0.0 or k[3] != 0.0 or tuple(k[6:]) != (0.0, 0.0, 1.0):
        raise InputError(
            f"topic {topic}: K = {k.tolist()} is not [fx 0 cx; 0 fy cy; 0 0 1] (no skew)", path
        )
    try:
        return Camera(
            int(msg.width), int(msg.height), k[0], k[4], k[2], k[5], dist  # type: ignore[arg-type]
        )
    except CameraParameterError as err:
        raise InputError(f"topic {topic}: {err}", path) from None


def _read_static_transforms(
    reader: AnyReader, path: Path, connections: Sequence[Any]
) -> dict[str, tuple[str, np.ndarray]]:
    """child frame → (parent frame, parent_T_child 4×4) from tf2_msgs/TFMessage messages."""
    edges: dict[str, tuple[str, np.ndarray]] = {}
    for _, msg in _messages(reader, path, connections):
        for tf in msg.transforms:
            t, q = tf.transform.translation, tf.transform.rotation
            matrix = np.eye(4)
            matrix[:3, :3] = _rotation_matrix(q.x, q.y, q.z, q.w)
            matrix[:3, 3] = (t.x, t.y, t.z)
            edges[_frame_name(tf.child_frame_id)] = (_frame_name(tf.header.frame_id), matrix)
    return edges


def _laser_pose(
    edges: dict[str, tuple[str, np.ndarray]], base: str, laser: str, path: Path, topic: str
) -> tuple[np.ndarray, bool]:
    """(robot_T_sensor (x, y, yaw), upside down?) from static transforms; zeros if unknown."""
    if not laser or laser == base:
        return np.zeros(3), False

    def to_root(frame: str) -> tuple[str, np.ndarray]:
        matrix, seen = np.eye(4), {frame}
        while frame in edges:
            parent, parent_T_child = edges[frame]
            if parent in seen:
                break  # a cycle: tf is a tree, so give up on it
            matrix, frame = parent_T_child @ matrix, parent
            seen.add(frame)
        return frame, matrix

    root_laser, root_T_laser = to_root(laser)
    root_base, root_T_base = to_root(base)
    if root_laser != root_base:
        warnings.warn(
            f"{path}: no static transform {base} → {laser} on {topic}; the laser is assumed "
            "at the robot's origin, facing forward (sensor_pose = 0)",
            RosbagWarning,
            stacklevel=3,
        )
        return np.zeros(3), False
    base_T_laser = np.linalg.inv(root_T_base) @ root_T_laser
    rotation = base_T_laser[:3, :3]
    flipped = rotation[2, 2] < 0.0  # the laser's z axis points down: its angles run clockwise
    tilt = math.acos(min(1.0, abs(rotation[2, 2])))
    if tilt > _MAX_LASER_TILT_RAD:
        warnings.warn(
            f"{path}: the laser frame {laser} is tilted {math.degrees(tilt):.1f}° from the "
            f"plane of {base}; its scans are used as if they were level",
            RosbagWarning,
            stacklevel=3,
        )
    yaw = math.atan2(rotation[1, 0], rotation[0, 0])  # the laser's x axis, in the plane
    return np.array([base_T_laser[0, 3], base_T_laser[1, 3], yaw]), bool(flipped)


def _rotation_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    q = np.array([x, y, z, w], dtype=np.float64)
    norm = np.linalg.norm(q)
    if not norm > 0.0:
        return np.eye(3)
    x, y, z, w = q / norm
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _frame_name(frame_id: str) -> str:
    return str(frame_id).lstrip("/")  # ROS 1 tf frames may carry a leading slash


def _span(trajectory: Trajectory) -> str:
    return f"[{trajectory.timestamps[0]:.9f}, {trajectory.timestamps[-1]:.9f}] s"


# --- sidecar, paths, validation ------------------------------------------------------------


def _sidecar_path(path: Path) -> Path:
    return path / SIDECAR_NAME if path.is_dir() else path.with_name(path.name + "." + SIDECAR_NAME)


def _read_sidecar(path: Path) -> dict | None:
    sidecar = _sidecar_path(path)
    if not sidecar.is_file():
        return None
    try:
        data = yaml.safe_load(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as err:
        raise InputError(f"cannot read the bag's sidecar: {err}", sidecar) from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(
            f"the sidecar must hold a mapping, got a {type(data).__name__}", sidecar
        )
    return data


def _sidecar_text(sidecar: dict) -> str:
    if not isinstance(sidecar, dict):
        raise ValueError(f"sidecar must be a dict, got {type(sidecar).__name__}")
    try:
        body = yaml.safe_dump(to_plain(sidecar), sort_keys=False, allow_unicode=True)
    except yaml.YAMLError as err:
        raise ValueError(f"sidecar is not YAML-serialisable: {err}") from None
    return (
        "# omnitof sidecar of the ROS 2 bag in this folder (omnitof.io.rosbag): the data the\n"
        "# bag's messages cannot carry. Metres, radians, seconds.\n" + body
    )


def _storage_plugin(storage: str) -> StoragePlugin:
    names = {"sqlite3": "SQLITE3", "mcap": "MCAP"}
    if storage not in names or not hasattr(StoragePlugin, names[storage]):
        available = [s for s, n in names.items() if hasattr(StoragePlugin, n)]
        raise ValueError(f"storage must be one of {available}, got {storage!r}")
    return getattr(StoragePlugin, names[storage])


def _checked_trajectory(trajectory: Trajectory, name: str) -> Trajectory:
    if not isinstance(trajectory, Trajectory):
        raise ValueError(f"{name} must be a Trajectory, got {type(trajectory).__name__}")
    if not np.all(np.isfinite(trajectory.poses)) or not np.all(
        np.isfinite(trajectory.timestamps)
    ):
        raise ValueError(f"{name} has non-finite poses or timestamps")
    if len(trajectory) == 0:
        raise ValueError(f"{name} has no pose")
    if np.any(np.diff(trajectory.timestamps) < 0):
        raise ValueError(f"{name} timestamps must not decrease")
    return trajectory


def _even_beams(angles: np.ndarray) -> tuple[float, float]:
    """(angle_min, angle_increment) of evenly spaced beams, else ValueError."""
    n = len(angles)
    if n == 0:
        raise ValueError("a LaserScan needs at least one beam")
    increment = 0.0 if n == 1 else (angles[-1] - angles[0]) / (n - 1)
    error = np.max(np.abs(angles - (angles[0] + increment * np.arange(n))))
    if error > _GEOMETRY_TOLERANCE:
        raise ValueError(
            f"a LaserScan needs evenly spaced beams; these deviate by up to {error:.3g} rad"
        )
    return float(angles[0]), float(increment)


def _fsync_tree(path: Path) -> None:
    """fsync every file under `path` (or the file itself) and the folders holding them."""
    paths = [path] if path.is_file() else [*sorted(path.rglob("*")), path]
    for p in paths:
        if p.is_file():
            with open(p, "rb") as handle:
                os.fsync(handle.fileno())
    for folder in {p if p.is_dir() else p.parent for p in paths}:
        _fsync_dir(folder)


def _fsync_dir(folder: Path) -> None:
    with suppress(OSError):  # not every platform / file system lets a folder be fsync'ed
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


@contextmanager
def _atomic_path(path: Path, overwrite: bool) -> Iterator[Path]:
    """Yield a not-yet-existing path to build a bag (file or folder) at; rename it to `path`.

    The bag is built as `.<name>.<random>.tmp/<name>` beside `path` (its inner name is the final
    one, so a ROS 2 bag's storage file is called `<name>.mcap`), synced to disk, and renamed
    into place only if the block succeeds; otherwise the staging folder is removed and `path`
    is left as it was.
    """
    if path.exists() and not overwrite:
        raise BagExistsError(f"{path} exists already; pass overwrite=True to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    while True:
        staging = path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")
        try:
            staging.mkdir()
            break
        except FileExistsError:
            continue
    try:
        inner = staging / path.name
        yield inner
        _fsync_tree(inner)
        old = staging / ".replaced"
        had_old = path.exists() or path.is_symlink()
        if had_old:
            os.replace(path, old)
        try:
            os.replace(inner, path)
        except BaseException:
            if had_old:
                os.replace(old, path)
            raise
        _fsync_dir(path.parent)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
