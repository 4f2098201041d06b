"""ToF bags (`write_tof_bag`, `read_tof_bag`): ToF images, camera info and odometry.

A ToF bag is a ROS 2 bag folder, MCAP storage by default (`DEFAULT_STORAGE`; "sqlite3" on
request), rosbag2 metadata version 8, message definitions from ROS 2 Humble (identical in later
distributions for the types used here); the reader takes ROS 1 bags too. Default topics
(`ToFTopics`):

    /tof/distance     sensor_msgs/Image       32FC1, metres: the camera's one-way radial distance
                                              (what the ToF measures), not the depth z
    /tof/amplitude    sensor_msgs/Image       32FC1, the amplitude A of paper eq. 3, sample units
    /tof/samples      sensor_msgs/Image       32FC4, optional: the raw samples, interleaved per
                                              pixel, channel k = A_k (one topic, not four)
    /tof/camera_info  sensor_msgs/CameraInfo  one per frame: width, height, K, R = I, P = [K|0],
                                              D "plumb_bob" (k1, k2, p1, p2, k3): OpenCV's order
    /odom             nav_msgs/Odometry       odom → base_link, at the trajectory's own timestamps;
                                              or the transform odom → base on /tf, or none
                                              (`omnitof.io.rosbag.odometry`)
    /ground_truth     nav_msgs/Odometry       world → base_link, optional (simulation)

The images and the camera info of one frame share one header stamp: that stamp *is* the frame's
timestamp, and the reader groups a frame's images by it (a driver's images stamped up to 5 ms
apart are paired too; the distance image's stamp is then the frame's). Each message's bag (log) time equals its
header stamp. Images are little-endian, rows packed (step = width · 4 · channels), pixel
[row, col] as in omnitof.sensor.camera. Odometry poses are planar: position (x, y, 0),
orientation the quaternion of a rotation by θ about +z, covariances and twist left zero
(unknown).

A camera driver's bag (read only) may name its topics otherwise (`ToFTopics`, `omnitof slam
--tof-topics`), carry distances as 16UC1 millimetres (REP 118; 0 = no reading) instead of 32FC1
metres, amplitudes as 16UC1 / mono16 / mono8, hold any of them as sensor_msgs/CompressedImage as
image_transport records them ("compressedDepth" PNG or RVL for the depth, PNG or JPEG otherwise;
`_decompressed`), and give the depth z along the optical axis
instead of the radial distance (`read_tof_bag(..., depth=True)`, `--tof-distance depth`): each
pixel's z is then divided by its unit ray's z component, which undoes what the driver did.

The sidecar (`<bag>/omnitof.yaml`), the all-or-nothing write and the time conversions are those
of `omnitof.io.rosbag.common`.
"""

from __future__ import annotations

import math
import warnings
from collections import OrderedDict
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from typing import Any

import numpy as np
from rosbags.rosbag2 import Writer as Writer2

from omnitof.errors import InputError
from omnitof.geometry import interpolate_poses
from omnitof.io.rosbag.common import (
    _ROSBAG2_VERSION,
    BASE_FRAME,
    CAMERA_FRAME,
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    DEFAULT_STORAGE,
    GROUND_TRUTH_TOPIC,
    IMAGE,
    IMAGE_TYPES,
    ODOM_FRAME,
    ODOMETRY,
    SIDECAR_NAME,
    TF_MESSAGE,
    TF_TOPIC,
    WORLD_FRAME,
    RosbagWarning,
    _atomic_path,
    _check_written_poses,
    _connections,
    _distinct_topics,
    _header,
    _messages,
    _ns_to_s,
    _opened,
    _PoseStream,
    parse_roles,
    _read_sidecar,
    _ros2_store,
    _sidecar_text,
    _stamp_ns,
    _storage_plugin,
    _to_ns,
)
from omnitof.io.rosbag.odometry import (
    TopicsOption,
    frames_without_slash,
    odometry_coverage,
    odometry_gaps,
    read_bag_odometry,
    scans_span_no_time,
    time_span,
)
from omnitof.sensor.camera import Camera, CameraParameterError
from omnitof.sensor.rig import Rig
from omnitof.types import Trajectory, first_non_finite

__all__ = ["ToFBag", "ToFFrameStamped", "ToFTopics", "read_tof_bag", "write_tof_bag"]

# Images of one frame that wait for their partners; more means a topic stopped publishing.
_MAX_PENDING_FRAMES = 64
# Images of one frame stamped this far apart (ns) are still paired: some drivers stamp each topic
# when they publish it. 5 ms is a quarter of a frame at 50 Hz, so two frames cannot be confused.
_PAIRING_NS = 5_000_000


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


# The raw samples' topic; another one named must be in the bag, this one may be absent.
SAMPLES_TOPIC = "/tof/samples"


@dataclass(frozen=True)
class ToFTopics:
    """Where a ToF bag keeps what `read_tof_bag` reads (`--tof-topics` in the CLI); the defaults
    are what `write_tof_bag` writes.

    distance, amplitude, samples, camera_info: the images and the camera's intrinsics.
    odometry: a nav_msgs/Odometry topic, or a tf2_msgs/TFMessage topic (such as "/tf") whose
        transform odom_frame → base_frame is the odometry; None: the one Odometry topic ("/odom"
        among several, never ground_truth), and where the bag has none, the transform on `tf`,
        and where tf has none either, no odometry (SLAM estimates it from the scans). The writer
        writes "/odom" for None.
    ground_truth: nav_msgs/Odometry of true poses, used where present.
    tf: the transform topic the odometry may be on.
    odom_frame: the odometry's fixed frame on tf.
    base_frame: the robot's frame that the odometry moves on tf; None: the one frame that
        odom_frame moves.
    """

    distance: str = "/tof/distance"
    amplitude: str = "/tof/amplitude"
    samples: str = SAMPLES_TOPIC
    camera_info: str = "/tof/camera_info"
    odometry: str | None = None
    ground_truth: str = GROUND_TRUTH_TOPIC
    tf: str = TF_TOPIC
    odom_frame: str = ODOM_FRAME
    base_frame: str | None = None

    def __post_init__(self) -> None:
        frames_without_slash(self)
        # The reader takes each topic for one role: the same topic for two would read one
        # role's messages as the other's.
        roles = {role: getattr(self, role) for role in ("distance", "amplitude", "samples", "camera_info",
                                                         "ground_truth")}
        if self.odometry is not None and self.odometry != self.tf:
            roles["odometry"] = self.odometry
        _distinct_topics(roles)

    @classmethod
    def parse(cls, text: str) -> ToFTopics:
        """Topics from "ROLE=TOPIC,ROLE=TOPIC" (the roles are the fields; the others keep their
        defaults), as `--tof-topics` takes them; ValueError naming a bad item."""
        return parse_roles(cls, text, "distance=/camera/distance")


# --- writing ToF bags ----------------------------------------------------------------------


def write_tof_bag(
    path: str | Path,
    frames: Iterable[ToFFrameStamped],
    *,
    camera: Camera,
    odometry: Trajectory | None,
    ground_truth: Trajectory | None = None,
    sidecar: dict | None = None,
    storage: str = DEFAULT_STORAGE,
    topics: ToFTopics = ToFTopics(),
    odometry_on_tf: bool = False,
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
        odometry: odometry poses (odom → base_link) with non-decreasing timestamps, or None for
            a bag without odometry (a camera carried by hand).
        ground_truth: true poses (world → base_link), or None.
        sidecar: a YAML-serialisable dict (numpy arrays and scalars are converted) written to
            `<bag>/omnitof.yaml`, or None for no sidecar.
        storage: "mcap" or "sqlite3".
        topics: topic names (the odometry on `topics.odometry`, "/odom" where it is None).
        odometry_on_tf: write the odometry as the transform `topics.odom_frame` →
            `topics.base_frame` (base_link where None) on `topics.tf` (tf2_msgs/TFMessage)
            instead of Odometry messages, as robots that publish it only to tf record it.
        overwrite: replace an existing bag at `path` (the old one is moved aside only once the
            new one is complete, and restored if the final rename fails).

    Returns:
        The number of frames written.

    Raises:
        BagExistsError: `path` exists and overwrite is False.
        ValueError: bad frames, trajectories or arguments, one topic for two roles (nothing is
            left at `path`).
    """
    path = Path(path)
    odometry_topic = topics.tf if odometry_on_tf else (topics.odometry or "/odom")
    written = ("distance", "amplitude", "samples", "camera_info", "ground_truth")
    roles = {f"topics.{role}": getattr(topics, role) for role in written}
    if odometry is not None:
        roles["topics.tf" if odometry_on_tf else "topics.odometry"] = odometry_topic
    _distinct_topics(roles)
    if odometry is not None and odometry_on_tf and topics.odom_frame == (topics.base_frame or BASE_FRAME):
        raise ValueError(f"topics.odom_frame and the base frame are both {topics.odom_frame!r}: the odometry is "
                         "the transform from the one frame to the other")
    plugin = _storage_plugin(storage)
    if path.suffix == ".bag":
        raise ValueError(
            f"{path}: a ROS 2 bag folder must not end in '.bag' (readers take that for ROS 1)"
        )
    if odometry is not None:
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
            pose_streams = []
            if odometry is not None:
                msgtype = TF_MESSAGE if odometry_on_tf else ODOMETRY
                pose_streams.append(
                    _PoseStream(
                        writer, writer.add_connection(odometry_topic, msgtype, typestore=store),
                        store, odometry, topics.odom_frame, topics.base_frame or BASE_FRAME, ros1=False,
                        as_tf=odometry_on_tf,
                    )
                )  # fmt: skip
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


def _checked_trajectory(trajectory: Trajectory, name: str) -> Trajectory:
    if not isinstance(trajectory, Trajectory):
        raise ValueError(f"{name} must be a Trajectory, got {type(trajectory).__name__}")
    if len(trajectory) == 0:
        raise ValueError(f"{name} has no pose")
    if first_non_finite(trajectory.timestamps) is not None:
        raise ValueError(f"{name} has non-finite timestamps")
    _check_written_poses(trajectory.poses, name)
    if np.any(np.diff(trajectory.timestamps) < 0):
        raise ValueError(f"{name} timestamps must not decrease")
    return trajectory


# --- reading ToF bags ----------------------------------------------------------------------


@dataclass
class ToFBag:
    """A ToF bag opened by `read_tof_bag`: metadata, trajectories and a streaming frame reader.

    Attributes:
        path: the bag.
        camera: intrinsics from the first camera_info message; None where it holds none (K all
            zeros, as drivers publish an uncalibrated camera: a calibration gives them).
        odometry: the odometry poses as recorded (their own timestamps), or None when the bag
            has none.
        ground_truth: the ground-truth poses as recorded, or None.
        sidecar: the sidecar dict (`<bag>/omnitof.yaml`), or None when there is none.
        topics: the topic names used.
        n_frames: the number of distance images in the bag.
        has_samples: whether the bag has the raw-samples topic.
        depth: the distance images hold the depth z along the optical axis, which the frames
            turn into the radial distance (module docstring).
        odometry_source: where the odometry came from, in words (its topic, or the transform on
            tf), "" without odometry.
    """

    path: Path
    camera: Camera | None
    odometry: Trajectory | None
    ground_truth: Trajectory | None
    sidecar: dict | None
    topics: ToFTopics
    n_frames: int
    has_samples: bool
    depth: bool = False
    odometry_source: str = ""
    shape: tuple[int, int] = (0, 0)  # (height, width) of the images, from camera_info
    _timestamps: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)
    _odometry_gaps: np.ndarray | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def rig(self) -> Rig | None:
        """The rig the sidecar describes (a simulated bag's true rig), or None without one;
        RigError naming the field if the sidecar's rig is broken."""
        if self.sidecar is None or "mirrors" not in self.sidecar:
            return None
        return Rig.from_dict(self.sidecar, self.path)

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
                not camera_info's, timestamps that go backwards, distance images that all share
                one stamp (stamps left unset), or a topic that stops.
        """
        roles = {self.topics.distance: "distance", self.topics.amplitude: "amplitude"}
        if samples and self.has_samples:
            roles[self.topics.samples] = "samples"
        shape = self.shape
        last_ns = dict.fromkeys(roles.values(), -1)
        pending: OrderedDict[int, dict[str, np.ndarray]] = OrderedDict()
        distance_ns: dict[int, int] = {}  # a pending frame's distance image's own stamp
        # Depth z = radial distance × the z component of the pixel's unit ray.
        ray_z = self.camera.pixel_grid_rays()[..., 2].astype(np.float32) if self.depth and self.camera else None
        emitted_ns = -1
        dropped: list[int] = []  # distance images without the frame's other images
        orphans = 0  # other images without a distance image
        repeated: list[int] = []  # images whose stamp repeats the one before on their topic
        distance_images, first_distance_ns = 0, -1
        with _opened(self.path) as reader:
            connections = [c for c in reader.connections if c.topic in roles]
            for conn, msg in _messages(reader, self.path, connections):
                role = roles[conn.topic]
                ns = _stamp_ns(msg.header.stamp)
                if role == "distance":
                    first_distance_ns = ns if distance_images == 0 else first_distance_ns
                    distance_images += 1
                if ns == last_ns[role]:  # the same image twice (a bag recorded from two sources)
                    repeated.append(ns)
                    continue
                if ns < last_ns[role]:
                    raise InputError(
                        f"topic {conn.topic}: timestamps go backwards: an image stamped "
                        f"{_ns_to_s(ns):.9f} s follows one stamped {_ns_to_s(last_ns[role]):.9f} s",
                        self.path,
                    )
                last_ns[role] = ns
                image = _decode_image(msg, self.path, conn.topic, IMAGE_FORMATS[role], shape, self.topics.camera_info,
                                      compressed=conn.msgtype == COMPRESSED_IMAGE, lossy=role != "distance")
                if role == "distance" and ray_z is not None:
                    image = image / ray_z
                key = _frame_key(pending, role, ns)
                pending.setdefault(key, {})[role] = image
                if role == "distance":
                    distance_ns[key] = ns
                while pending:
                    key, parts = next(iter(pending.items()))
                    missing = [r for r in last_ns if r not in parts]
                    if missing and not all(last_ns[r] > key + _PAIRING_NS for r in missing):
                        break  # its missing images may still come
                    del pending[key]
                    stamp = distance_ns.pop(key, key)
                    if missing:
                        if "distance" in parts:
                            dropped.append(stamp)
                        else:
                            orphans += 1
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
                        "the images of one frame must share one header stamp (or lie within 5 ms of it)",
                        self.path,
                    )
        for key, parts in pending.items():
            if "distance" in parts:
                dropped.append(distance_ns.get(key, key))
            else:
                orphans += 1
        # Every image read as a repeat of the first, one frame in all: stamps left unset, not a
        # bag recorded from two sources.
        if distance_images > 1 and last_ns["distance"] == first_distance_ns:
            raise scans_span_no_time(f"topic {self.topics.distance}", "images", distance_images, first_distance_ns,
                                     self.path)
        if repeated:
            warnings.warn(f"{self.path}: {len(repeated)} image(s) repeat the stamp of the one before on their "
                          f"topic (first at {_ns_to_s(repeated[0]):.9f} s); each read once", RosbagWarning,
                          stacklevel=2)
        if dropped and emitted_ns < 0:
            others = ", ".join(t for t, r in roles.items() if r != "distance")
            raise InputError(f"no frame is complete: no image of {others} lies within "
                             f"{_PAIRING_NS / 1e6:g} ms of any of the {len(dropped)} images of {self.topics.distance}",
                             self.path)
        if dropped:
            warnings.warn(
                f"{self.path}: skipped {len(dropped)} frame(s) whose images were incomplete "
                f"(first at {_ns_to_s(dropped[0]):.9f} s)"
                + (f", and {orphans} image(s) of no frame" if orphans else ""),
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
        """Odometry poses (N, 3) at `timestamps` (see interpolate_poses); NaN outside its span
        and in its holes (`odometry.odometry_gaps`: a pose interpolated across one is made up)."""
        if self.odometry is None:
            return np.full((np.size(timestamps), 3), np.nan)
        if self._odometry_gaps is None:
            self._odometry_gaps = odometry_gaps(self.odometry)
        t = np.atleast_1d(np.asarray(timestamps, dtype=np.float64))
        poses = interpolate_poses(self.odometry, t)
        for start, end in self._odometry_gaps:
            poses[(t > start) & (t < end)] = np.nan
        return poses

    def frame_odometry(self) -> Trajectory:
        """The odometry pose at every frame's timestamp, interpolated (InputError outside its
        span or in a hole)."""
        if self.odometry is None:
            raise InputError("the bag has no odometry", self.path)
        t = self.frame_timestamps()
        return self._at_frames(self.odometry, f"the odometry ({self.odometry_source})", self.odometry_at(t))

    def frame_ground_truth(self) -> Trajectory | None:
        """The true pose at every frame's timestamp, interpolated; None without ground truth."""
        if self.ground_truth is None:
            return None
        return self._at_frames(self.ground_truth, f"topic {self.topics.ground_truth}")

    def _at_frames(self, trajectory: Trajectory, what: str, poses: np.ndarray | None = None) -> Trajectory:
        t = self.frame_timestamps()
        poses = interpolate_poses(trajectory, t) if poses is None else poses
        outside = np.flatnonzero(np.isnan(poses[:, 0]))
        if outside.size:
            raise InputError(
                f"{what}: frame {outside[0]} at {t[outside[0]]:.9f} s is outside "
                + (odometry_coverage(trajectory) if trajectory is self.odometry
                   else f"its time span {time_span(trajectory)}"),
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
            pose = self.odometry_at(t)[0]
            odometry = None if np.isnan(pose[0]) else pose
        if self.ground_truth is not None:
            pose = interpolate_poses(self.ground_truth, t)[0]
            ground_truth = None if np.isnan(pose[0]) else pose
        return ToFFrameStamped(
            t, parts["distance"], parts["amplitude"], samples, odometry, ground_truth
        )


def _frame_key(pending: OrderedDict[int, dict[str, np.ndarray]], role: str, ns: int) -> int:
    """The pending frame an image of `role` stamped `ns` belongs to: the one of that stamp, else
    the nearest one within _PAIRING_NS that lacks this role, else a new one (`ns`)."""
    if ns in pending and role not in pending[ns]:
        return ns
    near = [s for s, parts in pending.items() if role not in parts and abs(s - ns) <= _PAIRING_NS]
    return min(near, key=lambda s: abs(s - ns)) if near else ns


# How the errors of `read_tof_bag` tell a user to choose a topic or frame.
_HOW = TopicsOption("--tof-topics", "ToFTopics")


def read_tof_bag(
    path: str | Path, *, topics: ToFTopics = ToFTopics(), require_odometry: bool = False, depth: bool = False,
    odometry: bool = True,
) -> ToFBag:
    """Open a ToF bag: read its camera, trajectories and sidecar; stream frames on demand.

    Reads any ROS 1 or ROS 2 bag with the topics of `topics` (the layout of the module
    docstring). Reading the frames is left to `ToFBag.frames()`, which streams them. The
    odometry is the Odometry topic, else the transform odom → base on /tf, else none
    (`ToFTopics.odometry`; `ToFBag.odometry_source` says which).

    Args:
        path: a ROS 2 bag folder (or bare .mcap/.db3 file), or a ROS 1 .bag file.
        topics: topic and frame names.
        require_odometry: refuse a bag without odometry (by default it is read with odometry
            None: a recording of a calibration target, a camera carried by hand).
        depth: the distance topic holds depth images (z along the optical axis), as many
            camera drivers publish them; the frames get the radial distance.
        odometry: False: do not look for the odometry at all (a calibration, a frame count):
            no topic choice to make, no pass over /tf.

    Raises:
        InputError: naming the bag (and the topic): not a bag, a missing topic or one of the
            wrong type, a camera_info omnitof's Camera cannot represent, odometry timestamps
            that go backwards, an unreadable sidecar, no odometry where it is required.
    """
    path = Path(path)
    with _opened(path) as reader:
        _connections(reader, path, topics.distance, IMAGE_TYPES)
        _connections(reader, path, topics.amplitude, IMAGE_TYPES)
        info = _connections(reader, path, topics.camera_info, CAMERA_INFO) or []
        samples = _connections(reader, path, topics.samples, IMAGE, required=topics.samples != SAMPLES_TOPIC)
        n_frames = sum(c.msgcount for c in reader.connections if c.topic == topics.distance)
        for topic in (topics.distance, topics.amplitude):
            if not any(c.msgcount for c in reader.connections if c.topic == topic):
                raise InputError(f"topic {topic}: has no message", path)
        shape = None
        for _, msg in _messages(reader, path, info):
            shape, camera = _camera_from_info(msg, path, topics.camera_info)
            break
        if shape is None:
            raise InputError(f"topic {topics.camera_info}: has no message", path)
        if camera is None and depth:
            raise InputError(f"topic {topics.camera_info}: K is all zeros (an uncalibrated camera), and depth "
                             "images need the intrinsics to give distances", path)
        found = read_bag_odometry(reader, path, odometry=topics.odometry, ground_truth=topics.ground_truth,
                                  tf=topics.tf, odom_frame=topics.odom_frame, base_frame=topics.base_frame,
                                  how=_HOW, find=odometry or require_odometry)
    if found.trajectory is None and require_odometry:
        raise InputError(
            f"the bag has no odometry: no {ODOMETRY} topic and no transform {topics.odom_frame} → base on "
            f"{topics.tf} (name them with {_HOW.choose('odometry')})",
            path,
        )
    return ToFBag(
        path=path,
        camera=camera,
        odometry=found.trajectory,
        ground_truth=found.ground_truth,
        sidecar=_read_sidecar(path),
        topics=topics,
        n_frames=n_frames,
        has_samples=samples is not None,
        depth=bool(depth),
        odometry_source=found.source,
        shape=shape,
    )


# The image encodings each role accepts: (numpy type, channels, scale to the role's unit, whether
# 0 means no reading). Distances in metres (16UC1: millimetres, REP 118, where 0 is no reading),
# amplitudes in the camera's own units.
IMAGE_FORMATS: dict[str, dict[str, tuple[str, int, float, bool]]] = {
    "distance": {"32FC1": ("f4", 1, 1.0, False), "16UC1": ("u2", 1, 0.001, True)},
    "amplitude": {"32FC1": ("f4", 1, 1.0, False), "16UC1": ("u2", 1, 1.0, False), "mono16": ("u2", 1, 1.0, False),
                  "mono8": ("u1", 1, 1.0, False)},
    "samples": {"32FC4": ("f4", 4, 1.0, False)},
}


def _decode_image(
    msg: Any, path: Path, topic: str, formats: dict[str, tuple[str, int, float, bool]],
    shape: tuple[int, int], info_topic: str, *, compressed: bool = False, lossy: bool = True,
) -> np.ndarray:  # fmt: skip
    """(H, W) or (H, W, channels) float32 pixels of a sensor_msgs/Image (or with `compressed` a
    CompressedImage: `_decompressed`, JPEG only where `lossy`) in one of `formats`
    (IMAGE_FORMATS), scaled to the role's unit, checked."""
    if compressed:
        encoding, raw = _decompressed(msg, path, topic, formats, lossy, shape)
        height, width = raw.shape[:2]
    else:
        encoding = str(msg.encoding)
        height, width = int(msg.height), int(msg.width)
    if encoding not in formats:
        raise InputError(
            f"topic {topic}: image encoding {encoding!r}, expected {' or '.join(repr(e) for e in formats)}", path
        )
    kind, channels, scale, zero_is_none = formats[encoding]
    if (height, width) != shape:
        raise InputError(
            f"topic {topic}: image of {width}×{height} pixels at "
            f"{_ns_to_s(_stamp_ns(msg.header.stamp)):.9f} s, but {info_topic} says "
            f"{shape[1]}×{shape[0]}",
            path,
        )
    if not compressed:
        row = width * np.dtype(kind).itemsize * channels
        data = np.asarray(msg.data, dtype=np.uint8)
        if msg.step < row or data.size != msg.step * height:
            raise InputError(
                f"topic {topic}: image step {msg.step} and {data.size} data bytes do not fit "
                f"{width}×{height} {encoding} pixels",
                path,
            )
        rows = data.reshape(height, msg.step)[:, :row].copy()  # copy: detach from the bag's buffer
        raw = rows.view((">" if msg.is_bigendian else "<") + kind)
    pixels = raw.astype(np.float32, copy=False)
    if scale != 1.0:
        pixels = pixels * np.float32(scale)
    if zero_is_none:
        pixels[raw == 0] = np.nan
    return pixels.reshape((height, width) if channels == 1 else (height, width, channels))


# image_transport's compressedDepth header: the kind of quantisation (image_transport writes 0,
# inverse depth), then its figures for a 32FC1 depth (depth = A / (q - B), q = 0 no reading),
# little-endian. PNG or RVL coding is said by the format string.
_DEPTH_HEADER = np.dtype([("compression", "<i4"), ("quant_a", "<f4"), ("quant_b", "<f4")])
# A PNG file's first 8 bytes, and its last 12 (the empty IEND chunk and its CRC).
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_PNG_END = b"\x00\x00\x00\x00IEND\xaeB`\x82"
# Plain image_transport formats ("png", "jpeg") name no pixel encoding: it follows from the pixels.
_BY_DTYPE = {np.dtype(np.uint16): ("16UC1", "mono16"), np.dtype(np.uint8): ("mono8",)}


def _decompressed(
    msg: Any, path: Path, topic: str, formats: dict[str, tuple[str, int, float, bool]], lossy: bool,
    shape: tuple[int, int],
) -> tuple[str, np.ndarray]:
    """(pixel encoding, pixels) of a sensor_msgs/CompressedImage as image_transport writes it:
    "ENCODING; compressedDepth [png|rvl]" (a depth image: `_DEPTH_HEADER`, then a 16-bit PNG, or
    the width and height (uint32) and an RVL stream, decoded by the core's `rvl_decode`: 16UC1
    as it is, 32FC1 as quantised inverse depth), "ENCODING; png|jpeg compressed ..." or a bare
    "png"/"jpeg" (decoded with OpenCV); single-channel only, of the bit depth its encoding says,
    an RVL image of `shape`. InputError naming the topic for a format it cannot read (colour, a
    corrupt image, JPEG where not `lossy`) or pixels that are not what the format string says."""
    import cv2

    fmt = str(msg.format)
    encoding, _, transport = (part.strip() for part in fmt.partition(";"))
    data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    stamp = f"{_ns_to_s(_stamp_ns(msg.header.stamp)):.9f} s"
    depth = "compresseddepth" in transport.lower()
    if depth:
        if data.size < _DEPTH_HEADER.itemsize:
            raise InputError(f"topic {topic}: the compressedDepth image at {stamp} holds {data.size} bytes", path)
        header = data[: _DEPTH_HEADER.itemsize].view(_DEPTH_HEADER)[0]
        data = data[_DEPTH_HEADER.itemsize:]
    image: np.ndarray | None
    if depth and "rvl" in transport.lower():
        image = _rvl_image(data, path, topic, stamp, shape)
    elif not lossy and any(word in fmt.lower() for word in ("jpeg", "jpg")):
        raise InputError(f"topic {topic}: {fmt!r} is lossy JPEG, which cannot carry distances; record them "
                         "as compressedDepth or png", path)
    elif data[:8].tobytes() == _PNG_SIGNATURE and data[-12:].tobytes() != _PNG_END:
        # Checked here: OpenCV would print libpng's own complaint before failing.
        raise InputError(f"topic {topic}: the {fmt!r} image at {stamp} is a truncated PNG ({data.size} bytes, "
                         "no end chunk)", path)
    else:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if image is None:
        raise InputError(f"topic {topic}: cannot decode the {fmt!r} image at {stamp}", path)
    if image.ndim != 2:
        raise InputError(f"topic {topic}: the {fmt!r} image at {stamp} has {image.shape[2]} channels; a ToF "
                         "image has one", path)
    bits = f"{image.dtype.itemsize * 8}-bit"
    if encoding.lower() in ("png", "jpeg", "jpg") and not transport:
        inferred = [e for e in _BY_DTYPE.get(image.dtype, ()) if e in formats]
        if not inferred:
            raise InputError(f"topic {topic}: the {fmt!r} image at {stamp} holds {bits} pixels, which are not "
                             f"{' or '.join(repr(e) for e in formats)}", path)
        encoding = inferred[0]
    if encoding in formats and not (depth and encoding == "32FC1"):
        kind = np.dtype(formats[encoding][0])
        if image.dtype != kind:
            raise InputError(f"topic {topic}: the {fmt!r} image at {stamp} holds {bits} pixels, not the "
                             f"{kind.itemsize * 8}-bit ones of {encoding}", path)
    if depth and encoding == "32FC1":
        # image_transport's figures give every q >= 1 a positive depth (A > 0, B < 1: A = d(d+1),
        # B = 1 - d for its depth_quantization d); others would make distances out of nothing.
        if image.dtype != np.uint16:
            raise InputError(f"topic {topic}: the compressedDepth image at {stamp} holds {bits} pixels; its "
                             "quantised depth is 16-bit", path)
        a, b = float(header["quant_a"]), float(header["quant_b"])
        if not (math.isfinite(a) and math.isfinite(b) and a > 0 and b < 1):
            raise InputError(f"topic {topic}: the compressedDepth image at {stamp} has quantisation A = {a:g}, "
                             f"B = {b:g}; depth = A / (q - B) needs A > 0 and B < 1", path)
        q = image.astype(np.float32)
        with np.errstate(divide="ignore"):
            metres = np.float32(header["quant_a"]) / (q - np.float32(header["quant_b"]))
        return encoding, np.where(image == 0, np.float32(np.nan), metres).astype(np.float32)
    return encoding, image


def _rvl_image(data: np.ndarray, path: Path, topic: str, stamp: str, shape: tuple[int, int]) -> np.ndarray:
    """The uint16 pixels of compressed_depth_image_transport's RVL payload: width and height
    (uint32, little-endian), then the RVL stream (rust/src/rvl.rs)."""
    from omnitof import _core

    if data.size < 8:
        raise InputError(f"topic {topic}: the RVL image at {stamp} holds {data.size} bytes", path)
    width, height = (int(v) for v in data[:8].view("<u4"))
    if (height, width) != shape:  # checked first: the size decides how much memory the decoder takes
        raise InputError(f"topic {topic}: the RVL image at {stamp} says {width}×{height} pixels, the camera "
                         f"{shape[1]}×{shape[0]}", path)
    try:
        return _core.rvl_decode(np.ascontiguousarray(data[8:]), height * width).reshape(height, width)
    except ValueError as err:
        raise InputError(f"topic {topic}: the image at {stamp}: {err}", path) from err


def _camera_from_info(msg: Any, path: Path, topic: str) -> tuple[tuple[int, int], Camera | None]:
    """The (height, width) of the images and omnitof's Camera from a sensor_msgs/CameraInfo
    (plumb_bob, no skew), None for the camera where K is all zeros (a driver's uncalibrated
    camera: the rig's calibration has the intrinsics); ROS 1 names its fields K and D, ROS 2 k
    and d."""
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64)
    d = [float(v) for v in (msg.d if hasattr(msg, "d") else msg.D)]
    width, height = int(msg.width), int(msg.height)
    if width <= 0 or height <= 0:
        raise InputError(f"topic {topic}: images of {width}×{height} pixels", path)
    if not k.any():
        return (height, width), None
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
        return (height, width), Camera(width, height, k[0], k[4], k[2], k[5], dist)  # type: ignore[arg-type]
    except CameraParameterError as err:
        raise InputError(f"topic {topic}: {err}", path) from None
