"""Tests of omnitof.io.rosbag: ToF bags and laser-scan bags, written into tmp_path.

Round trips go through the module's own writers; the bags that must be malformed (or must come
from "another tool", such as a ROS 1 bag with a tf tree) are written message by message with
rosbags directly, so that the reader is checked against data its writer did not make.
"""

from __future__ import annotations

import math
import re
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2

from omnitof.sensor.camera import Camera
from omnitof.errors import InputError
from omnitof.io.rosbag import (
    DEFAULT_STORAGE,
    SIDECAR_NAME,
    BagExistsError,
    LaserTopics,
    RosbagWarning,
    ToFFrameStamped,
    ToFTopics,
    bag_message_types,
    from_ros_time,
    interpolate_poses,
    read_laserscan_bag,
    read_tof_bag,
    to_ros_time,
    write_laserscan_bag,
    write_tof_bag,
)
from omnitof.types import ScanSequence, Trajectory
from bag_messages import (
    HUMBLE,
    NOETIC,
    NS,
    ODOM,
    OLD_TF,
    SCAN,
    TF,
    header,
    odometry_msg,
    read_warned,
    scan_msg,
    tf_msg,
    write_raw,
)

IMG = "sensor_msgs/msg/Image"
INFO = "sensor_msgs/msg/CameraInfo"
SMALL = Camera(8, 6, 10.0, 11.0, 3.5, 2.5, (-0.1, 0.01, 0.001, -0.002, 0.0003))


def angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * (np.asarray(a) - np.asarray(b))))


def assert_poses(actual: np.ndarray, expected: np.ndarray, atol: float = 1e-9) -> None:
    np.testing.assert_allclose(actual[:, :2], expected[:, :2], rtol=0, atol=atol)
    np.testing.assert_allclose(angle_diff(actual[:, 2], expected[:, 2]), 0.0, atol=atol)


def bits(a: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=np.float32).view(np.uint32)


def make_frames(
    camera: Camera, n: int, *, samples: bool, seed: int = 0
) -> list[ToFFrameStamped]:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        distance = rng.uniform(0.0, 7.5, camera.shape).astype(np.float32)
        distance[0, 0] = np.nan  # special values must survive bit for bit
        distance[0, 1] = np.inf
        distance[1, 0] = -0.0
        amplitude = rng.exponential(100.0, camera.shape).astype(np.float32)
        raw = rng.uniform(0, 4000, (4, *camera.shape)).astype(np.float32) if samples else None
        frames.append(ToFFrameStamped(1700000000.0 + 0.1 * i, distance, amplitude, raw))
    return frames


def trajectory(t: np.ndarray, seed: int) -> Trajectory:
    rng = np.random.default_rng(seed)
    poses = np.column_stack(
        [rng.normal(0, 5, len(t)), rng.normal(0, 5, len(t)), rng.uniform(-np.pi, np.pi, len(t))]
    )
    return Trajectory(t, poses)


# --- raw bags written with rosbags directly (their other messages: bag_messages) -----------


def image_msg(ns: int, array: np.ndarray, encoding: str = "32FC1"):
    data = np.ascontiguousarray(array)
    channels = 1 if data.ndim == 2 else data.shape[2]
    return HUMBLE.types[IMG](
        header=header(HUMBLE, ns, "cam"),
        height=data.shape[0],
        width=data.shape[1],
        encoding=encoding,
        is_bigendian=0,
        step=data.shape[1] * data.itemsize * channels,
        data=data.reshape(-1).view(np.uint8),
    )


def camera_info_msg(ns: int, camera: Camera):
    t = HUMBLE.types
    return t[INFO](
        header=header(HUMBLE, ns, "cam"),
        height=camera.height,
        width=camera.width,
        distortion_model="plumb_bob",
        d=np.array(camera.dist),
        k=camera.K.reshape(-1),
        r=np.eye(3).reshape(-1),
        p=np.zeros(12),
        binning_x=0,
        binning_y=0,
        roi=t["sensor_msgs/msg/RegionOfInterest"](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False
        ),
    )


def raw_tof_bag(path: Path, stamps_ns, *, camera=SMALL, shape=None, encoding="32FC1",
                skip_amplitude=(), odom_stamps_ns=None) -> Path:  # fmt: skip
    """A ToF bag: per stamp camera_info, distance and amplitude; odometry at odom_stamps_ns."""
    shape = shape or camera.shape
    dtype = np.uint16 if encoding == "16UC1" else np.float32
    messages: list[tuple[str, str, object]] = []
    odom_stamps_ns = stamps_ns if odom_stamps_ns is None else odom_stamps_ns
    for k, ns in enumerate(odom_stamps_ns):
        messages.append(("/odom", ODOM, odometry_msg(HUMBLE, ns, (k, 0, 0))))
    for ns in stamps_ns:
        messages.append(("/tof/camera_info", INFO, camera_info_msg(ns, camera)))
        image = np.full(shape, ns / NS, dtype=dtype)
        messages.append(("/tof/distance", IMG, image_msg(ns, image, encoding)))
        if ns not in skip_amplitude:
            messages.append(("/tof/amplitude", IMG, image_msg(ns, image)))
    return write_raw(path, messages)


# --- ROS time ------------------------------------------------------------------------------


def test_ros_time() -> None:
    assert to_ros_time(1.5) == (1, 500_000_000)
    assert to_ros_time(0.1 * 3) == (0, 300_000_000)
    assert to_ros_time(0.9999999999) == (1, 0)
    t = 1700000000.123456789  # an epoch time: its float resolves ~0.24 µs
    sec, nanosec = to_ros_time(t)
    assert sec == 1700000000 and abs(from_ros_time(sec, nanosec) - t) <= 1e-9 * t
    assert abs(nanosec - 123456789) <= 120  # within the float's own resolution
    for bad in (-0.1, math.nan, math.inf, 1e300, 2.0**31):  # 1e300 was a bare struct.error in the writer
        with pytest.raises(ValueError, match="a ROS bag time must be finite, >= 0 s and before 2038-01-19"):
            to_ros_time(bad)


# --- ToF bags ------------------------------------------------------------------------------


@pytest.mark.parametrize("storage", ["mcap", "sqlite3"])
def test_tof_round_trip(tmp_path: Path, storage: str) -> None:
    camera = Camera.sr4000()
    frames = make_frames(camera, 6, samples=True)
    # Odometry at 20 Hz, ground truth at 10 Hz: their own timestamps, not the frames'.
    odometry = trajectory(1700000000.0 - 0.05 + 0.05 * np.arange(14), seed=1)
    truth = trajectory(1700000000.0 + 0.1 * np.arange(6), seed=2)
    sidecar = {
        "world": "corridor1",
        "mirrors": {"count": 4, "tilt_deg": 45.0, "normals": np.eye(3)[:2]},
        "camera": {"fx": np.float64(249.58), "dist": list(camera.dist)},
    }
    path = tmp_path / "seq"
    n = write_tof_bag(
        path, iter(frames), camera=camera, odometry=odometry, ground_truth=truth,
        sidecar=sidecar, storage=storage,
    )  # fmt: skip
    assert n == 6
    assert sorted(p.name for p in path.iterdir()) == sorted(
        ["metadata.yaml", f"seq.{'mcap' if storage == 'mcap' else 'db3'}", SIDECAR_NAME]
    )
    assert [p.name for p in tmp_path.iterdir()] == ["seq"]  # no staging folder left

    bag = read_tof_bag(path)
    assert bag.camera == camera  # width, height, fx, fy, cx, cy and dist, exactly
    assert bag.n_frames == len(bag) == 6 and bag.has_samples
    assert bag.sidecar == {
        "world": "corridor1",
        "mirrors": {"count": 4, "tilt_deg": 45.0, "normals": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]},
        "camera": {"fx": 249.58, "dist": list(camera.dist)},
    }
    np.testing.assert_allclose(bag.odometry.timestamps, odometry.timestamps, rtol=0, atol=1e-9)
    assert_poses(bag.odometry.poses, odometry.poses)
    np.testing.assert_allclose(bag.ground_truth.timestamps, truth.timestamps, rtol=0, atol=1e-9)
    assert_poses(bag.ground_truth.poses, truth.poses)

    back = list(bag.frames())
    assert len(back) == 6
    for got, sent in zip(back, frames):
        assert abs(got.timestamp - sent.timestamp) <= 1e-9 * sent.timestamp
        for name in ("distance", "amplitude", "samples"):
            a, b = getattr(got, name), getattr(sent, name)
            assert a.dtype == np.float32 and a.shape == b.shape
            np.testing.assert_array_equal(bits(a), bits(b))  # bit-exact, NaN and -0 included
        assert_poses(got.odometry[None], interpolate_poses(odometry, sent.timestamp))
        assert_poses(got.ground_truth[None], truth.poses[[back.index(got)]])
    assert all(f.samples is None for f in bag.frames(samples=False))
    np.testing.assert_allclose(
        bag.frame_timestamps(), [f.timestamp for f in frames], rtol=0, atol=1e-6
    )
    assert_poses(bag.frame_ground_truth().poses, truth.poses)


def test_tof_bag_without_samples_or_ground_truth(tmp_path: Path) -> None:
    frames = make_frames(SMALL, 3, samples=False)
    odometry = trajectory(np.array([frames[0].timestamp, frames[-1].timestamp]), seed=3)
    write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry)
    bag = read_tof_bag(tmp_path / "b")
    assert not bag.has_samples and bag.ground_truth is None and bag.sidecar is None
    assert bag.frame_ground_truth() is None
    got = list(bag)
    assert [f.samples for f in got] == [None] * 3
    np.testing.assert_array_equal(bits(got[2].amplitude), bits(frames[2].amplitude))


def test_tof_bag_odometry_on_tf_or_none(tmp_path: Path) -> None:
    # A camera on a robot that publishes its odometry only to tf, and one carried by hand.
    frames = make_frames(SMALL, 4, samples=False)
    odometry = trajectory(frames[0].timestamp - 0.05 + 0.05 * np.arange(9), seed=4)
    write_tof_bag(tmp_path / "tf", frames, camera=SMALL, odometry=odometry, odometry_on_tf=True)
    bag = read_tof_bag(tmp_path / "tf")
    assert bag.odometry_source == "the transform odom → base_link on /tf"
    np.testing.assert_allclose(bag.odometry.timestamps, odometry.timestamps, rtol=0, atol=1e-9)
    assert_poses(bag.odometry.poses, odometry.poses)
    assert_poses(np.array([f.odometry for f in bag.frames()]), interpolate_poses(odometry, [f.timestamp for f in frames]))
    # Named frames that tf does not have are an error naming the option.
    with pytest.raises(InputError, match=r"no transform odom → base_footprint .*--tof-topics odom_frame=FRAME"):
        read_tof_bag(tmp_path / "tf", topics=ToFTopics(base_frame="base_footprint"))
    write_tof_bag(tmp_path / "none", frames, camera=SMALL, odometry=None)
    bag = read_tof_bag(tmp_path / "none")
    assert bag.odometry is None and all(f.odometry is None for f in bag.frames())
    # An Odometry topic on another name is found by its type.
    write_tof_bag(tmp_path / "wheel", frames, camera=SMALL, odometry=odometry, topics=ToFTopics(odometry="/wheel_odom"))
    bag = read_tof_bag(tmp_path / "wheel")
    assert bag.odometry_source == "/wheel_odom"
    assert_poses(bag.odometry.poses, odometry.poses)


def test_tof_odometry_by_type_skips_empty_topics_and_can_be_left_alone(tmp_path: Path) -> None:
    stamps = [NS, 2 * NS]
    base = raw_tof_bag(tmp_path / "base", stamps, odom_stamps_ns=[])
    from rosbags.highlevel import AnyReader

    with AnyReader([base]) as reader:  # the frames of a bag without odometry, to copy
        frames = [(c.topic, c.msgtype, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    # Two Odometry topics, one declared but never published (ROS 2 bags record those): the other.
    store = HUMBLE
    writer_path = tmp_path / "two"
    with Writer2(writer_path, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        writer.add_connection("/empty_odom", ODOM, typestore=store)
        conns = {}
        for k, (topic, msgtype, msg) in enumerate(frames + [("/wheel", ODOM, odometry_msg(store, ns, (k, 0, 0)))
                                                            for k, ns in enumerate(stamps)]):
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], (k + 1) * 1000, store.serialize_cdr(msg, msgtype))
    bag = read_tof_bag(writer_path)
    assert bag.odometry_source == "/wheel" and len(bag.odometry) == 2
    # Two published Odometry topics: a choice to make, unless the odometry is not wanted (a
    # calibration), which then reads the bag without it.
    both = write_raw(tmp_path / "both", frames + [(t, ODOM, odometry_msg(store, NS, (0, 0, 0))) for t in ("/a", "/b")])
    expect_error(both, "several nav_msgs/msg/Odometry topics: /a, /b", "--tof-topics odometry=TOPIC")
    assert read_tof_bag(both, odometry=False).odometry is None
    # A named odometry topic that is not there lists both kinds it could have been.
    expect_error(base, "topic /tf (nav_msgs/msg/Odometry or tf2_msgs/msg/TFMessage) is missing",
                 topics=ToFTopics(odometry="/tf"))


def test_frames_stream_lazily(tmp_path: Path) -> None:
    """The writer pulls frames one by one; the reader hands out a frame before reading on."""
    pulled = []

    def generate():
        for frame in make_frames(SMALL, 5, samples=False):
            pulled.append(frame.timestamp)
            yield frame

    t = Trajectory([1700000000.0, 1700000001.0], np.zeros((2, 3)))
    write_tof_bag(tmp_path / "b", generate(), camera=SMALL, odometry=t)
    assert len(pulled) == 5
    frames = read_tof_bag(tmp_path / "b").frames()
    first = next(frames)
    assert first.timestamp == pytest.approx(1700000000.0)
    frames.close()


def test_interpolation_analytic(tmp_path: Path) -> None:
    # Odometry at t = 0 and 1: from (0, 0, 170°) to (1, 2, -170°); the shorter arc crosses ±180°.
    start, end = [0.0, 0.0, math.radians(170)], [1.0, 2.0, math.radians(-170)]
    odometry = Trajectory([0.0, 1.0], [start, end])
    expected = {
        0.25: (0.25, 0.5, math.radians(175)),
        0.5: (0.5, 1.0, math.radians(180)),
        0.75: (0.75, 1.5, math.radians(-175)),
        1.0: (1.0, 2.0, math.radians(-170)),
    }
    poses = interpolate_poses(odometry, list(expected))
    assert_poses(poses, np.array(list(expected.values())), atol=1e-12)
    assert np.isnan(interpolate_poses(odometry, [-0.1, 1.1])).all()
    # Equal timestamps (a repeated message) are allowed and take the later pose.
    steps = Trajectory([0.0, 1.0, 1.0, 2.0], [[0, 0, 0], [1, 0, 0], [5, 0, 0], [6, 0, 0]])
    np.testing.assert_allclose(interpolate_poses(steps, [0.5, 1.5])[:, 0], [0.5, 5.5])

    # Through a bag: frames at 0.25 s and 0.75 s get exactly these poses, the frame at 1.5 s none.
    frames = [
        ToFFrameStamped(t, np.zeros(SMALL.shape), np.zeros(SMALL.shape)) for t in (0.25, 0.75, 1.5)
    ]
    write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry)
    bag = read_tof_bag(tmp_path / "b")
    got = list(bag.frames())
    assert_poses(np.array([got[0].odometry, got[1].odometry]), poses[[0, 2]], atol=1e-12)
    assert got[2].odometry is None
    with pytest.raises(InputError, match="/odom.*frame 2 at 1.5"):
        bag.frame_odometry()


def test_write_is_atomic(tmp_path: Path) -> None:
    frames = make_frames(SMALL, 4, samples=False)
    odometry = trajectory(np.array([frames[0].timestamp]), seed=0)

    def failing():
        yield from frames[:2]
        raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError, match="interrupted"):
        write_tof_bag(tmp_path / "b", failing(), camera=SMALL, odometry=odometry, sidecar={})
    assert list(tmp_path.iterdir()) == []  # neither a bag nor a staging folder

    # Bad input found midway (a timestamp going backwards) leaves nothing either.
    frames[2].timestamp = frames[0].timestamp
    with pytest.raises(ValueError, match="timestamps must increase"):
        write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry)
    assert list(tmp_path.iterdir()) == []

    frames[2].timestamp = frames[1].timestamp + 0.1
    write_tof_bag(tmp_path / "b", frames[:3], camera=SMALL, odometry=odometry)
    with pytest.raises(BagExistsError):
        write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry)
    with pytest.raises(RuntimeError):
        write_tof_bag(tmp_path / "b", failing(), camera=SMALL, odometry=odometry, overwrite=True)
    assert read_tof_bag(tmp_path / "b").n_frames == 3  # the old bag is untouched
    write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry, overwrite=True)
    assert read_tof_bag(tmp_path / "b").n_frames == 4
    assert [p.name for p in tmp_path.iterdir()] == ["b"]


def test_overwrite_replaces_a_bag_and_nothing_else(tmp_path: Path, monkeypatch) -> None:
    # The writer replaces its target as a whole: with overwrite it deleted a folder of the
    # user's own, or a plain file, and "." crashed it.
    from omnitof.errors import OutputError

    frames = make_frames(SMALL, 2, samples=False)
    odometry = trajectory(np.array([0.0, 0.1, 0.2]), seed=0)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep me")
    (tmp_path / "notes.txt").write_text("keep me")
    for target, message in [("mine", "not a ROS 2 bag (it holds notes.txt)"), ("notes.txt", "not a ROS 1 bag"),
                            (".", "holds the current folder"), ("mine/..", "holds the current folder")]:
        with pytest.raises(OutputError, match=re.escape(message)):
            write_tof_bag(target, frames, camera=SMALL, odometry=odometry, overwrite=True)
    assert (tmp_path / "mine" / "notes.txt").read_text() == (tmp_path / "notes.txt").read_text() == "keep me"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "notes.txt"]
    write_tof_bag("bag", frames, camera=SMALL, odometry=odometry)  # a bag, its sidecar: replaced
    write_tof_bag("bag", frames[:1], camera=SMALL, odometry=odometry, overwrite=True, sidecar={})
    assert read_tof_bag(tmp_path / "bag").n_frames == 1


@pytest.mark.parametrize("case, message", [
    ("mount point", "bag: is a mount point: a bag is written by replacing it as a whole; give the bag a new name"),
    ("bind mount", "bag: is a mount point"),  # os.path.ismount misses one within a file system
    ("immutable", "bag: the bag cannot be replaced (Operation not permitted), and a bag is written by replacing "
                  "it as a whole: give another path for the bag"),
])
def test_overwrite_refuses_a_bag_that_cannot_be_replaced_before_writing(tmp_path: Path, monkeypatch, unreplaceable,
                                                                        case, message) -> None:
    # The finished bag takes its target's place by a rename: at a mount point (a Docker volume)
    # or an immutable folder that failed only after every frame had been written.
    from omnitof.errors import OutputError

    frames = make_frames(SMALL, 2, samples=False)
    odometry = trajectory(np.array([0.0, 0.1, 0.2]), seed=0)
    write_tof_bag(tmp_path / "bag", frames[:1], camera=SMALL, odometry=odometry)
    unreplaceable(tmp_path / "bag", case)

    def frames_written():
        written.append(1)
        yield from frames

    written: list[int] = []
    with pytest.raises(OutputError, match=re.escape(message)):
        write_tof_bag(tmp_path / "bag", frames_written(), camera=SMALL, odometry=odometry, overwrite=True)
    assert written == []  # refused before the first frame
    monkeypatch.undo()
    assert read_tof_bag(tmp_path / "bag").n_frames == 1
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]


def test_writer_rejects_bad_arguments(tmp_path: Path) -> None:
    frames = make_frames(SMALL, 2, samples=False)
    odometry = trajectory(np.array([0.0]), seed=0)
    with pytest.raises(ValueError, match="camera's"):
        write_tof_bag(tmp_path / "a", frames, camera=Camera.sr4000(), odometry=odometry)
    with pytest.raises(ValueError, match="storage"):
        write_tof_bag(tmp_path / "a", frames, camera=SMALL, odometry=odometry, storage="zip")
    with pytest.raises(ValueError, match="'.bag'"):
        write_tof_bag(tmp_path / "a.bag", frames, camera=SMALL, odometry=odometry)
    with pytest.raises(ValueError, match="at least one frame"):
        write_tof_bag(tmp_path / "a", [], camera=SMALL, odometry=odometry)
    mixed = make_frames(SMALL, 2, samples=True)
    mixed[1].samples = None
    with pytest.raises(ValueError, match="raw samples"):
        write_tof_bag(tmp_path / "a", mixed, camera=SMALL, odometry=odometry)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"distance": "/odom"}, "topics.distance and topics.odometry are both '/odom'"),
        # Refused by ToFTopics itself, for the reader as for the writer.
        ({"amplitude": "/tof/distance"}, "distance and amplitude are both '/tof/distance'"),
        ({"samples": "/cam", "ground_truth": "/cam"}, "samples and ground_truth are both '/cam'"),
        ({"odometry": "/ground_truth"}, "ground_truth and odometry are both '/ground_truth'"),
    ],
)
def test_tof_writer_refuses_one_topic_for_two_roles(tmp_path: Path, given: dict, message: str) -> None:
    frames = make_frames(SMALL, 2, samples=False)
    odometry = trajectory(np.array([f.timestamp for f in frames]), seed=4)
    with pytest.raises(ValueError, match=f"{re.escape(message)}: each needs a topic of its own"):
        write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry, topics=ToFTopics(**given))
    assert list(tmp_path.iterdir()) == []


def test_custom_topics(tmp_path: Path) -> None:
    topics = ToFTopics(distance="/cam/depth", amplitude="/cam/ampl", odometry="/wheel_odom")
    frames = make_frames(SMALL, 2, samples=False)
    odometry = trajectory(np.array([f.timestamp for f in frames]), seed=4)
    write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=odometry, topics=topics)
    bag = read_tof_bag(tmp_path / "b", topics=topics)
    assert len(list(bag.frames())) == 2
    with pytest.raises(InputError) as err:
        read_tof_bag(tmp_path / "b")
    assert "/tof/distance" in str(err.value) and "/cam/depth" in str(err.value)  # lists topics


# --- ToF bag errors: each names the bag and the topic --------------------------------------


def expect_error(path: Path, *fragments: str, **kwargs) -> InputError:
    with pytest.raises(InputError) as info:
        bag = read_tof_bag(path, **kwargs)
        list(bag.frames())
    message = str(info.value)
    assert str(path) in message and info.value.path == path
    for fragment in fragments:
        assert fragment in message, message
    return info.value


def test_not_a_bag(tmp_path: Path) -> None:
    text = tmp_path / "notes.txt"
    text.write_text("hello\n")
    expect_error(text, "not a readable ROS bag")
    fake = tmp_path / "fake.bag"
    fake.write_bytes(b"#ROSBAG V1.2\n garbage")
    expect_error(fake, "not a readable ROS bag")
    folder = tmp_path / "folder"
    folder.mkdir()
    expect_error(folder, "not a readable ROS bag")
    expect_error(tmp_path / "absent", "no such bag")
    (folder / "metadata.yaml").write_text("foo: [\n")  # rosbags' YAML error spans four lines
    assert "\n" not in str(expect_error(folder, "not a readable ROS bag (Could not load YAML"))


def test_missing_and_mistyped_topics(tmp_path: Path) -> None:
    stamps = [NS, 2 * NS]
    path = raw_tof_bag(tmp_path / "b", stamps)
    expect_error(path, "topic /tof/samples", "missing",
                 topics=ToFTopics(samples="/x", distance="/tof/samples"))  # fmt: skip
    expect_error(path, "topic /gt", "missing", "/tof/distance (sensor_msgs/msg/Image)",
                 topics=ToFTopics(odometry="/gt"))  # fmt: skip
    expect_error(path, "topic /odom has type nav_msgs/msg/Odometry",
                 "expected sensor_msgs/msg/CameraInfo",
                 topics=ToFTopics(camera_info="/odom"))  # fmt: skip
    with pytest.raises(ValueError, match="distance and camera_info are both '/tof/distance'"):
        ToFTopics(camera_info="/tof/distance")
    # A bag without odometry is read (SLAM estimates it from the scans), unless it is required.
    bare = raw_tof_bag(tmp_path / "bare", stamps, odom_stamps_ns=[])
    bag = read_tof_bag(bare)
    assert bag.odometry is None and bag.odometry_source == "" and [f.odometry for f in bag.frames()] == [None, None]
    expect_error(bare, "the bag has no odometry", "--tof-topics odometry=TOPIC", require_odometry=True)
    with pytest.raises(InputError, match="the bag has no odometry"):
        bag.frame_odometry()


def test_wrong_encoding(tmp_path: Path) -> None:
    path = raw_tof_bag(tmp_path / "b", [NS], encoding="bgr8")
    expect_error(path, "topic /tof/distance", "encoding 'bgr8'", "expected '32FC1' or '16UC1'")


def test_a_drivers_bag_depth_in_millimetres(tmp_path: Path) -> None:
    # A camera driver's layout: its own topic names, the depth z along the optical axis in
    # 16UC1 millimetres (0: no reading), the amplitude as mono8.
    topics = ToFTopics(distance="/cam/depth/image_raw", amplitude="/cam/amplitude/image_raw",
                       camera_info="/cam/depth/camera_info", odometry="/wheel_odom")
    rng = np.random.default_rng(5)
    depth_mm = rng.integers(300, 7000, size=SMALL.shape).astype(np.uint16)
    depth_mm[1, 2] = 0
    amplitude = rng.integers(0, 255, size=SMALL.shape).astype(np.uint8)
    messages = [("/wheel_odom", ODOM, odometry_msg(HUMBLE, ns, (k, 0, 0))) for k, ns in enumerate([NS, 2 * NS])]
    messages += [("/cam/depth/camera_info", INFO, camera_info_msg(NS, SMALL)),
                 ("/cam/depth/image_raw", IMG, image_msg(NS, depth_mm, "16UC1")),
                 ("/cam/amplitude/image_raw", IMG, image_msg(NS, amplitude, "mono8"))]
    path = write_raw(tmp_path / "driver", messages)
    (frame,) = list(read_tof_bag(path, topics=topics, depth=True).frames())
    # The radial distance: z over the z component of each pixel's unit ray (through the lens's
    # distortion), computed here from the camera's own ray of each pixel.
    v, u = np.mgrid[0:SMALL.height, 0:SMALL.width]
    rays = SMALL.rays(np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)).reshape(*SMALL.shape, 3)
    expected = depth_mm * 0.001 / (rays[..., 2] / np.linalg.norm(rays, axis=2))
    expected[1, 2] = np.nan
    np.testing.assert_allclose(frame.distance, expected, rtol=1e-6)
    seen = depth_mm > 0
    assert np.isnan(frame.distance[1, 2]) and np.all(frame.distance[seen] >= depth_mm[seen] * 0.001 - 1e-6)
    np.testing.assert_array_equal(frame.amplitude, amplitude.astype(np.float32))
    # Read as radial distances, the same bag gives the millimetres in metres.
    (radial,) = list(read_tof_bag(path, topics=topics).frames())
    np.testing.assert_allclose(radial.distance[seen], depth_mm[seen] * 0.001, rtol=1e-6)
    # The calibration reads such a bag the same way (`omnitof calibrate ... --tof-topics`).
    from omnitof.calibration.images import load_images

    (image,) = load_images([path], topics=topics, depth=True)
    np.testing.assert_array_equal(image.distance, frame.distance)
    np.testing.assert_array_equal(image.amplitude, frame.amplitude)
    with pytest.raises(InputError, match="/tof/distance"):
        load_images([path])


COMPRESSED = "sensor_msgs/msg/CompressedImage"


def compressed_msg(ns: int, fmt: str, data: bytes):
    return HUMBLE.types[COMPRESSED](header=header(HUMBLE, ns, "cam"), format=fmt,
                                    data=np.frombuffer(data, dtype=np.uint8))


def png(array: np.ndarray) -> bytes:
    ok, buffer = cv2.imencode(".png", array)
    assert ok
    return buffer.tobytes()


def rvl(pixels: np.ndarray) -> bytes:
    """compressed_depth_image_transport's RVL payload (after its 12-byte header): width and
    height as uint32, then the pixels coded as Wilson's RVL paper gives the coder (runs of zeros
    and of readings, zigzag differences, 3-bit groups in 4-bit codes, eight codes per
    little-endian 32-bit word, the first in the top bits)."""
    codes: list[int] = []

    def put(value: int) -> None:
        while True:
            code, value = value & 7, value >> 3
            codes.append(code | (8 if value else 0))
            if not value:
                return

    flat = [int(p) for p in pixels.ravel()]
    i, previous = 0, 0
    while i < len(flat):
        zeros = next((k for k, p in enumerate(flat[i:]) if p), len(flat) - i)
        put(zeros)
        i += zeros
        readings = next((k for k, p in enumerate(flat[i:]) if not p), len(flat) - i)
        put(readings)
        for p in flat[i:i + readings]:
            delta = p - previous
            put(2 * delta if delta >= 0 else -2 * delta - 1)  # zigzag: (d << 1) ^ (d >> 31)
            previous = p
        i += readings
    codes += [0] * (-len(codes) % 8)
    words = [sum(c << (28 - 4 * k) for k, c in enumerate(codes[j:j + 8])) for j in range(0, len(codes), 8)]
    return np.array(pixels.shape[::-1], "<u4").tobytes() + np.array(words, "<u4").tobytes()


def quantised(a: float, b: float) -> bytes:
    """compressedDepth's 12-byte header for a 32FC1 depth quantised as z = a / (q - b)."""
    return np.array([(0, a, b)], dtype=[("c", "<i4"), ("a", "<f4"), ("b", "<f4")]).tobytes()


def test_a_drivers_bag_recorded_compressed(tmp_path: Path, capfd) -> None:
    # image_transport's compressed topics, as a bag recorded with them holds them: the depth
    # "compressedDepth" (a 12-byte header, then a 16-bit PNG), the amplitude a PNG or a JPEG.
    rng = np.random.default_rng(6)
    depth_mm = rng.integers(300, 7000, size=SMALL.shape).astype(np.uint16)
    depth_mm[0, 3] = 0  # no reading
    amplitude = rng.integers(0, 60000, size=SMALL.shape).astype(np.uint16)
    header16 = np.zeros(1, dtype=[("c", "<i4"), ("a", "<f4"), ("b", "<f4")]).tobytes()
    # 32FC1 depth goes as its quantised inverse: q = A / z + B, so that z = A / (q - B).
    a, b = 1000.0, -1.0
    metres = rng.uniform(0.4, 7.0, SMALL.shape).astype(np.float32)
    q = np.round(a / metres + b).astype(np.uint16)
    q[2, 1] = 0
    header32 = np.array([(0, a, b)], dtype=[("c", "<i4"), ("a", "<f4"), ("b", "<f4")]).tobytes()
    topics = ToFTopics(distance="/cam/depth/compressedDepth", amplitude="/cam/amplitude/compressed",
                       camera_info="/cam/camera_info")
    messages = [("/odom", ODOM, odometry_msg(HUMBLE, ns, (k, 0, 0))) for k, ns in enumerate([NS, 3 * NS])]
    messages += [("/cam/camera_info", INFO, camera_info_msg(NS, SMALL)),
                 (topics.distance, COMPRESSED, compressed_msg(NS, "16UC1; compressedDepth png", header16 + png(depth_mm))),
                 (topics.amplitude, COMPRESSED, compressed_msg(NS, "mono16; png compressed mono16", png(amplitude))),
                 ("/cam/camera_info", INFO, camera_info_msg(2 * NS, SMALL)),
                 (topics.distance, COMPRESSED, compressed_msg(2 * NS, "32FC1; compressedDepth", header32 + png(q))),
                 (topics.amplitude, COMPRESSED, compressed_msg(2 * NS, "png", png(amplitude))),
                 ("/cam/camera_info", INFO, camera_info_msg(3 * NS, SMALL)),
                 (topics.distance, COMPRESSED, compressed_msg(3 * NS, "16UC1; compressedDepth rvl", header16 + rvl(depth_mm))),
                 (topics.amplitude, COMPRESSED, compressed_msg(3 * NS, "mono16; png compressed mono16", png(amplitude)))]
    path = write_raw(tmp_path / "compressed", messages)
    first, second, third = read_tof_bag(path, topics=topics).frames()
    expected = depth_mm * np.float32(0.001)
    expected[0, 3] = np.nan
    np.testing.assert_array_equal(first.distance, expected)
    np.testing.assert_array_equal(first.amplitude, amplitude.astype(np.float32))
    # The inverse quantisation: within half a step of q, and no reading where q is 0.
    step = metres**2 / a
    seen = q > 0
    assert np.isnan(second.distance[2, 1]) and np.all(np.abs(second.distance - metres)[seen] <= 0.5 * step[seen] + 1e-5)
    np.testing.assert_array_equal(second.amplitude, amplitude.astype(np.float32))
    # RVL (the core's decoder against the paper's coder above): the same millimetres.
    np.testing.assert_array_equal(third.distance, expected)
    # A broken RVL stream or one of another size, colour, a corrupt image, JPEG distances and
    # pixels of another bit depth are named.
    eight_bit = png(depth_mm.astype(np.uint8))
    for fmt, data, fragment in [("16UC1; compressedDepth rvl", header16 + rvl(depth_mm)[:-8], "RVL: the stream ends early"),
                                ("16UC1; compressedDepth rvl", header16 + rvl(depth_mm[:2]), "says 8×2 pixels, the camera 8×6"),
                                ("16UC1; compressedDepth png", header16 + eight_bit, "holds 8-bit pixels, not the 16-bit"),
                                ("png", eight_bit, "holds 8-bit pixels, which are not '32FC1' or '16UC1'"),
                                ("mono8; jpeg compressed mono8", cv2.imencode(".jpg", depth_mm.astype(np.uint8))[1].tobytes(),
                                 "lossy JPEG"),
                                ("bgr16; png compressed bgr16", png(np.zeros((*SMALL.shape, 3), np.uint16)), "3 channels"),
                                ("16UC1; compressedDepth png", header16 + b"not a png", "cannot decode"),
                                ("16UC1; compressedDepth png", header16 + png(depth_mm)[:-20], "is a truncated PNG"),
                                # The quantisation of a 32FC1 depth, which would make distances of nothing.
                                ("32FC1; compressedDepth png", header32 + eight_bit, "its quantised depth is 16-bit"),
                                ("32FC1; compressedDepth png", quantised(0.0, -1.0) + png(q), "A = 0, B = -1"),
                                ("32FC1; compressedDepth png", quantised(np.nan, -1.0) + png(q), "A = nan"),
                                ("32FC1; compressedDepth png", quantised(1000.0, 5.0) + png(q), "needs A > 0 and B < 1")]:
        bad = messages[:3] + [(topics.distance, COMPRESSED, compressed_msg(NS, fmt, data)), messages[4]]
        expect_error(write_raw(tmp_path / fragment.replace(" ", "_").replace("/", "_"), bad), fragment,
                     topics.distance, topics=topics)
    assert "libpng" not in capfd.readouterr().err  # one message, omnitof's, for the truncated PNG


def test_image_size_mismatch(tmp_path: Path) -> None:
    path = raw_tof_bag(tmp_path / "b", [NS], shape=(5, 8))
    expect_error(path, "topic /tof/distance", "8×5", "/tof/camera_info says 8×6")


def test_image_timestamps_backwards(tmp_path: Path) -> None:
    path = raw_tof_bag(tmp_path / "b", [NS, 3 * NS, 2 * NS], odom_stamps_ns=[NS, 3 * NS])
    expect_error(
        path, "topic /tof/distance", "go backwards", "2.000000000 s follows", "3.000000000 s"
    )


def test_odometry_timestamps_backwards(tmp_path: Path) -> None:
    path = raw_tof_bag(tmp_path / "b", [NS, 2 * NS], odom_stamps_ns=[2 * NS, NS])
    expect_error(path, "topic /odom", "go backwards")


def test_unsupported_camera_info(tmp_path: Path) -> None:
    info = camera_info_msg(NS, SMALL)
    info.distortion_model = "equidistant"
    info.d = np.array([0.1, 0.2, 0.3, 0.4])
    path = write_raw(tmp_path / "b", [
        ("/odom", ODOM, odometry_msg(HUMBLE, NS, (0, 0, 0))),
        ("/tof/camera_info", INFO, info),
        ("/tof/distance", IMG, image_msg(NS, np.zeros(SMALL.shape, np.float32))),
        ("/tof/amplitude", IMG, image_msg(NS, np.zeros(SMALL.shape, np.float32))),
    ])  # fmt: skip
    expect_error(path, "topic /tof/camera_info", "equidistant")


def test_a_ros1_tof_bag(tmp_path: Path) -> None:
    # ROS 1's CameraInfo names its matrices K and D (ROS 2: k and d); headers carry a seq.
    t = NOETIC.types
    info = t[INFO](header=header(NOETIC, NS, "cam"), height=SMALL.height, width=SMALL.width,
                   distortion_model="plumb_bob", D=np.array(SMALL.dist), K=SMALL.K.reshape(-1),
                   R=np.eye(3).reshape(-1), P=np.zeros(12), binning_x=0, binning_y=0,
                   roi=t["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                              do_rectify=False))
    messages = []
    for k in (1, 2):
        image = np.full(SMALL.shape, float(k), np.float32)
        msg = t[IMG](header=header(NOETIC, k * NS, "cam"), height=SMALL.height, width=SMALL.width, encoding="32FC1",
                     is_bigendian=0, step=SMALL.width * 4, data=image.reshape(-1).view(np.uint8))
        messages += [("/odom", ODOM, odometry_msg(NOETIC, k * NS, (k, 0, 0))), ("/tof/camera_info", INFO, info),
                     ("/tof/distance", IMG, msg), ("/tof/amplitude", IMG, msg)]
    bag = read_tof_bag(write_raw(tmp_path / "b.bag", messages, ros1=True))
    assert bag.camera == SMALL
    frames = list(bag.frames())
    assert [f.timestamp for f in frames] == [1.0, 2.0] and float(frames[1].distance[0, 0]) == 2.0
    assert_poses(np.array([f.odometry for f in frames]), np.array([[1.0, 0, 0], [2.0, 0, 0]]))


def test_an_uncalibrated_camera_info_gives_the_image_size_alone(tmp_path: Path) -> None:
    # Drivers publish K all zeros for a camera never calibrated (as for a calibration's own
    # recording): the frames are read, the intrinsics come from the rig's calibration.
    info = camera_info_msg(NS, SMALL)
    info.k = np.zeros(9)
    info.d = np.zeros(5)
    image = np.full(SMALL.shape, 2.0, np.float32)
    path = write_raw(tmp_path / "b", [("/tof/camera_info", INFO, info), ("/tof/distance", IMG, image_msg(NS, image)),
                                      ("/tof/amplitude", IMG, image_msg(NS, image))])
    bag = read_tof_bag(path)
    assert bag.camera is None and bag.shape == SMALL.shape
    (frame,) = bag.frames()
    np.testing.assert_array_equal(frame.distance, image)
    # Depth images cannot be turned into distances without the intrinsics.
    expect_error(path, "topic /tof/camera_info", "K is all zeros", depth=True)


def test_an_image_sent_twice_is_read_once(tmp_path: Path) -> None:
    messages = [("/odom", ODOM, odometry_msg(HUMBLE, k * NS, (k, 0, 0))) for k in (1, 2)]
    for k in (1, 2):
        image = image_msg(k * NS, np.full(SMALL.shape, float(k), np.float32))
        messages += [("/tof/camera_info", INFO, camera_info_msg(k * NS, SMALL)), ("/tof/distance", IMG, image),
                     ("/tof/amplitude", IMG, image)]
        if k == 1:
            messages.append(("/tof/distance", IMG, image))  # the same stamp again
    path = write_raw(tmp_path / "b", messages)
    with pytest.warns(RosbagWarning, match=r"1 image\(s\) repeat the stamp .*\(first at 1\.0+ s\); each read once"):
        frames = list(read_tof_bag(path).frames())
    assert [f.timestamp for f in frames] == [1.0, 2.0]


def test_images_whose_stamps_were_left_unset_are_refused(tmp_path: Path) -> None:
    # A driver with use_sim_time and no /clock stamps every image 0. Before, each image after
    # the first read as the first recorded again (a warning), and SLAM ran on one frame.
    path = raw_tof_bag(tmp_path / "b", [0, 0, 0], odom_stamps_ns=[0, NS])
    expect_error(path, "topic /tof/distance: the 3 images span no time (every one is stamped 0.000000000 s): "
                       "their header stamps were left unset, as by a node with use_sim_time and no /clock")
    # One frame spans no time and needs none.
    assert len(list(read_tof_bag(raw_tof_bag(tmp_path / "one", [0], odom_stamps_ns=[0, NS])).frames())) == 1


def test_images_that_never_pair_and_a_topic_without_messages_are_named(tmp_path: Path) -> None:
    # The amplitude stamped 20 ms after the distance (beyond the 5 ms that make one frame).
    messages = [("/odom", ODOM, odometry_msg(HUMBLE, k * NS, (k, 0, 0))) for k in (1, 2, 3)]
    for k in (1, 2, 3):
        image = np.full(SMALL.shape, float(k), np.float32)
        messages += [("/tof/camera_info", INFO, camera_info_msg(k * NS, SMALL)),
                     ("/tof/distance", IMG, image_msg(k * NS, image)),
                     ("/tof/amplitude", IMG, image_msg(k * NS + 20_000_000, image))]
    path = write_raw(tmp_path / "late", messages)
    with pytest.raises(InputError, match=r"no frame is complete: no image of /tof/amplitude lies within 5 ms of any "
                                         r"of the 3 images of /tof/distance") as info:
        list(read_tof_bag(path).frames())
    assert info.value.path == path
    # A topic declared in the bag but never published (ROS 2 bags record such topics).
    empty = write_raw(tmp_path / "empty", [m for m in messages if m[0] != "/tof/amplitude"],
                      declared=[("/tof/amplitude", IMG)])
    expect_error(empty, "topic /tof/amplitude: has no message")


def test_incomplete_frame_is_skipped(tmp_path: Path) -> None:
    path = raw_tof_bag(tmp_path / "b", [NS, 2 * NS, 3 * NS], skip_amplitude={2 * NS})
    bag = read_tof_bag(path)
    with pytest.warns(RosbagWarning, match="skipped 1 frame"):
        got = list(bag.frames())
    assert [f.timestamp for f in got] == [1.0, 3.0]
    np.testing.assert_array_equal(got[1].distance, np.full(SMALL.shape, 3.0, np.float32))


def test_images_stamped_a_little_apart_are_one_frame(tmp_path: Path) -> None:
    # A driver that stamps each topic when it publishes it: the amplitude 2 ms after the
    # distance (and once 2 ms before); a 40 ms gap is another frame, whose partner never comes.
    messages = [("/odom", ODOM, odometry_msg(HUMBLE, k * NS, (k, 0, 0))) for k in range(5)]
    offsets = {NS: 2_000_000, 2 * NS: -2_000_000, 3 * NS: 40_000_000}
    for ns, dt in offsets.items():
        messages.append(("/tof/camera_info", INFO, camera_info_msg(ns, SMALL)))
        if dt < 0:
            messages.append(("/tof/amplitude", IMG, image_msg(ns + dt, np.full(SMALL.shape, 7.0, np.float32))))
        messages.append(("/tof/distance", IMG, image_msg(ns, np.full(SMALL.shape, ns / NS, np.float32))))
        if dt > 0:
            messages.append(("/tof/amplitude", IMG, image_msg(ns + dt, np.full(SMALL.shape, 7.0, np.float32))))
    path = write_raw(tmp_path / "b", messages)
    # One frame's distance without its amplitude, and that amplitude's image of no frame.
    with pytest.warns(RosbagWarning, match=r"skipped 1 frame\(s\) .*\(first at 3\.0+ s\), and 1 image\(s\) of no frame"):
        got = list(read_tof_bag(path).frames())
    # The frames take the distance image's stamp, as frame_timestamps() does.
    assert [f.timestamp for f in got] == [1.0, 2.0]
    assert [float(f.distance[0, 0]) for f in got] == [1.0, 2.0] and all(f.amplitude[0, 0] == 7.0 for f in got)


def test_topic_that_stops(tmp_path: Path) -> None:
    stamps = [k * NS for k in range(1, 71)]
    path = raw_tof_bag(tmp_path / "b", stamps, skip_amplitude=set(stamps[3:]))
    expect_error(path, "topic /tof/amplitude", "no image for the frame at 4.000000000 s")


def test_bad_sidecar(tmp_path: Path) -> None:
    frames = make_frames(SMALL, 1, samples=False)
    write_tof_bag(tmp_path / "b", frames, camera=SMALL, odometry=trajectory(np.array([0.0]), 0))
    (tmp_path / "b" / SIDECAR_NAME).write_text("- a list\n- not a mapping\n")
    with pytest.raises(InputError, match="mapping") as info:
        read_tof_bag(tmp_path / "b")
    assert info.value.path == tmp_path / "b" / SIDECAR_NAME
    # An empty sidecar, or one of a newer format, is said so (both read as "no calibration", or
    # half-understood).
    for text, message in [("", "the bag's sidecar is empty"), ("omnitof_sidecar: 99\n", "omnitof_sidecar: 99: this "
                          "omnitof reads sidecars of version 1 or older"), ("omnitof_sidecar: one\n", "omnitof_sidecar: 'one'")]:
        (tmp_path / "b" / SIDECAR_NAME).write_text(text)
        with pytest.raises(InputError, match=message):
            read_tof_bag(tmp_path / "b")
    (tmp_path / "b" / SIDECAR_NAME).write_text("omnitof_sidecar: 1\nnotes: a field of a later version 1\n")
    assert read_tof_bag(tmp_path / "b").sidecar["notes"].startswith("a field")


# --- laser-scan bags -----------------------------------------------------------------------


def scan_sequence(n: int = 12, beams: int = 360, seed: int = 0) -> ScanSequence:
    rng = np.random.default_rng(seed)
    ranges = rng.uniform(0.05, 7.4, (n, beams)).astype(np.float32)
    ranges[rng.random((n, beams)) < 0.2] = np.inf
    return ScanSequence(
        timestamps=1300000000.0 + 0.1 * np.arange(n) + rng.uniform(0, 0.01, n),
        ranges=ranges,
        angles=np.radians(np.arange(beams) - 180.0),
        odometry=np.column_stack([rng.normal(0, 3, (n, 2)), rng.uniform(-np.pi, np.pi, n)]),
        sensor_pose=np.array([0.12, -0.03, 0.25]),
        max_range=7.5,
        remissions=rng.uniform(0, 1000, (n, beams)).astype(np.float32),
        ground_truth=np.column_stack([rng.normal(0, 3, (n, 2)), rng.uniform(-3, 3, n)]),
    )


@pytest.mark.parametrize("version, name", [(1, "scans.bag"), (2, "scans")])
def test_laserscan_round_trip(tmp_path: Path, version: int, name: str) -> None:
    scans = scan_sequence()
    path = tmp_path / name
    write_laserscan_bag(path, scans, version=version)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complete bag reads without a warning
        back = read_laserscan_bag(path)
    assert back.source == str(path)
    np.testing.assert_array_equal(back.ranges, scans.ranges)  # inf (no echo) preserved
    assert np.isinf(back.ranges).sum() == np.isinf(scans.ranges).sum() > 0
    np.testing.assert_array_equal(back.remissions, scans.remissions)
    np.testing.assert_allclose(back.timestamps, scans.timestamps, rtol=0, atol=1e-9 * 1.3e9)
    np.testing.assert_allclose(back.angles, scans.angles, rtol=0, atol=1e-6)  # float32 fields
    assert back.max_range == np.float32(7.5)
    assert_poses(back.odometry, scans.odometry)
    assert_poses(back.ground_truth, scans.ground_truth)
    assert_poses(back.sensor_pose[None], scans.sensor_pose[None])


def test_scans_without_odometry_are_written_without_it_and_read_back_so(tmp_path: Path) -> None:
    import dataclasses

    from omnitof.io.carmen import write_carmen

    scans = dataclasses.replace(scan_sequence(), odometry=np.zeros((12, 3)), odometry_known=False)
    write_laserscan_bag(tmp_path / "bare.bag", scans, version=1)
    back = read_laserscan_bag(tmp_path / "bare.bag")
    assert not back.odometry_known and back.odometry_rule.startswith("none")
    np.testing.assert_array_equal(back.ranges, scans.ranges)
    assert_poses(back.ground_truth, scans.ground_truth)
    # A CARMEN log holds a pose per scan: zeros would read as a robot standing still.
    with pytest.raises(ValueError, match="no odometry, and a CARMEN log holds one pose per scan"):
        write_carmen(tmp_path / "bare.clf", scans)
    assert not (tmp_path / "bare.clf").exists()


@pytest.mark.parametrize("mode", ["FILE", "MESSAGE"])
def test_a_ros2_bag_compressed_with_zstd_reads_as_the_plain_one(tmp_path: Path, mode: str) -> None:
    # `ros2 bag record --compression-mode file|message --compression-format zstd`, as users
    # record long logs: the same scans come back.
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import CompressionFormat, CompressionMode

    scans = scan_sequence()
    write_laserscan_bag(tmp_path / "plain", scans, version=2)
    packed = tmp_path / "packed"
    with AnyReader([tmp_path / "plain"]) as reader:
        writer = Writer2(packed, version=8, storage_plugin=StoragePlugin.SQLITE3)
        writer.set_compression(CompressionMode[mode], CompressionFormat.ZSTD)
        with writer:
            conns = {c.id: writer.add_connection(c.topic, c.msgtype, typestore=reader.typestore)
                     for c in reader.connections}
            for conn, stamp, raw in reader.messages():
                writer.write(conns[conn.id], stamp, raw)
    back, plain = read_laserscan_bag(packed), read_laserscan_bag(tmp_path / "plain")
    np.testing.assert_array_equal(back.ranges, plain.ranges)
    assert_poses(back.odometry, plain.odometry)
    assert_poses(back.sensor_pose[None], scans.sensor_pose[None])


def interlaced_sequence(n: int = 12, seed: int = 0) -> ScanSequence:
    """scan_sequence's scans with per-scan geometry: 181 beams from -90°, then 180 beams from
    -89.75°, -89.5°, -89.25° in turn, all at 1° (an interlaced SICK)."""
    from omnitof.types import evenly_spaced_beams

    base = scan_sequence(n, beams=181, seed=seed)
    offsets = np.array([0.0, 0.25, 0.5, 0.75])[np.arange(n) % 4]
    counts = np.where(offsets == 0.0, 181, 180)
    angles, beam_counts = evenly_spaced_beams(np.radians(-90 + offsets), np.full(n, np.radians(1.0)),
                                              counts, tolerance=1e-9)
    return ScanSequence(base.timestamps, base.ranges, angles, base.odometry, sensor_pose=base.sensor_pose,
                        max_range=base.max_range, remissions=base.remissions, ground_truth=base.ground_truth,
                        beam_counts=beam_counts)


@pytest.mark.parametrize("version, name", [(1, "scans.bag"), (2, "scans")])
def test_laserscan_round_trip_with_varying_geometry(tmp_path: Path, version: int, name: str) -> None:
    scans = interlaced_sequence()
    path = tmp_path / name
    write_laserscan_bag(path, scans, version=version)
    back = read_laserscan_bag(path)
    assert back.per_scan_geometry
    np.testing.assert_array_equal(back.beam_counts, scans.beam_counts)
    np.testing.assert_array_equal(back.ranges, scans.ranges)  # padding is +inf on both sides
    np.testing.assert_array_equal(back.remissions, scans.remissions)
    np.testing.assert_allclose(back.angles, scans.angles, rtol=0, atol=1e-6)  # NaN padding equal
    for i in (0, 1, 5):
        assert len(back.scan_angles(i)) == len(back.scan_ranges(i)) == scans.beam_counts[i]
    assert back.max_range == np.float32(7.5) and back.max_range_rule == "LaserScan range_max"
    assert_poses(back.odometry, scans.odometry)


def test_laserscan_bag_with_changing_beams_and_range_max(tmp_path: Path) -> None:
    # Another tool's bag: the count, start angle and range_max change between messages.
    messages: list[tuple[str, str, object]] = []
    for k in range(4):
        ns = 1000 * NS + k * NS // 10
        messages.append(("/odom", ODOM, odometry_msg(HUMBLE, ns, (0.1 * k, 0, 0))))
        beams = [3.0] * (4 + k % 2)
        messages.append(("/scan", SCAN, scan_msg(HUMBLE, ns, beams, angle_min=-1.0 + 0.25 * (k % 2),
                                                 rmax=4.0 if k < 3 else 2.5)))  # fmt: skip
    with pytest.warns(RosbagWarning, match="no static transform"):
        scans = read_laserscan_bag(write_raw(tmp_path / "varying", messages))
    np.testing.assert_array_equal(scans.beam_counts, [4, 5, 4, 5])
    np.testing.assert_allclose(scans.scan_angles(1), -0.75 + 0.5 * np.arange(5), atol=1e-7)
    np.testing.assert_allclose(scans.scan_angles(2), -1.0 + 0.5 * np.arange(4), atol=1e-7)
    np.testing.assert_array_equal(scans.scan_ranges(2), np.float32([3.0] * 4))
    assert np.isinf(scans.scan_ranges(3)).all()  # 3 m > that scan's range_max of 2.5 m
    assert scans.max_range == 4.0 and scans.max_range_rule == "LaserScan range_max (2.5 to 4 m)"


def test_laserscan_range_max_inf_takes_the_maximum_from_the_readings(tmp_path: Path) -> None:
    # pointcloud_to_laserscan's default range_max (the largest double) is +inf as a float32: no
    # limit. The maximum is then a no-echo code repeated at the top of the readings, where one is
    # (as read_carmen finds 50.00 m), else just beyond the farthest reading (an echo, kept).
    def bag(name: str, far: list[float]) -> ScanSequence:
        messages: list[tuple[str, str, object]] = []
        for k in range(120):  # a code must repeat at least 100 times (carmen.TOP_VALUE_MIN_COUNT)
            ns = 1000 * NS + k * NS // 10
            messages.append(("/odom", ODOM, odometry_msg(HUMBLE, ns, (0.01 * k, 0, 0))))
            beams = [1.0 + 0.01 * k, 2.0 + 0.003 * k, far[k % len(far)], math.inf]
            messages.append(("/scan", SCAN, scan_msg(HUMBLE, ns, beams, rmax=math.inf)))
        return read_warned(write_raw(tmp_path / name, messages))[0]

    plain = bag("plain", [6.25, 7.5, 3.0])
    assert plain.max_range > 7.5 and plain.max_range == np.nextafter(np.float32(7.5), np.float32(np.inf))
    assert plain.max_range_rule == "the farthest reading, 7.5 m (range_max not finite)"
    np.testing.assert_array_equal(plain.ranges[:3, 2], np.float32([6.25, 7.5, 3.0]))  # every reading an echo
    assert np.isinf(plain.ranges[:, 3]).all()
    coded = bag("coded", [50.0])  # a driver's no-echo code on one beam of four
    assert coded.max_range == 50.0 and coded.max_range_rule.startswith("repeated top value 50 m (120 readings")
    assert np.isinf(coded.ranges[:, 2]).all()


def test_laserscan_beams_that_are_no_lasers_are_refused_and_a_wrong_angle_max_warned_of(tmp_path: Path) -> None:
    def bag(name, **geometry):
        messages = []
        for k in range(2):
            ns = 1000 * NS + k * NS // 10
            messages += [("/odom", ODOM, odometry_msg(HUMBLE, ns, (0.1 * k, 0, 0))),
                         ("/scan", SCAN, scan_msg(HUMBLE, ns, [3.0] * 5, **geometry))]
        return write_raw(tmp_path / name, messages)

    # As the CARMEN reader refuses them: every beam at one bearing, beams beyond ±2π.
    expect = [("zero", {"inc": 0.0}, "angle_increment 0: it would put all 5 beams at one bearing"),
              ("tiny", {"inc": 1e-300}, "it would put all 5 beams at one bearing"),
              ("beyond", {"angle_min": -100.0}, "put its 5 beams at -100 .. -98 rad; a laser's beams lie within ±2π"),
              ("wide", {"inc": 10.0}, "-1 .. 39 rad; a laser's beams lie within ±2π")]
    for name, geometry, fragment in expect:
        with pytest.raises(InputError, match=re.escape(fragment)) as info:
            read_laserscan_bag(bag(name, **geometry))
        assert "topic /scan: the scan at 1000.000000000 s" in str(info.value)
    # An angle_max that disagrees with the beams: they are placed as LaserScan defines them.
    messages = [("/odom", ODOM, odometry_msg(HUMBLE, 1000 * NS, (0, 0, 0))),
                ("/scan", SCAN, scan_msg(HUMBLE, 1000 * NS, [3.0] * 5))]
    messages[1][2].angle_max = -0.5  # the last of 5 beams from -1 rad every 0.5 rad is at 1 rad
    with pytest.warns(RosbagWarning, match=r"1 scan\(s\) end elsewhere than their angle_max says; .* the last at 1 "
                                           r"rad, but angle_max -0\.5 rad"):
        scans = read_laserscan_bag(write_raw(tmp_path / "odd_max", messages))
    np.testing.assert_allclose(scans.scan_angles(0), -1.0 + 0.5 * np.arange(5), atol=1e-7)


@pytest.mark.parametrize("version, name", [(1, "jitter.bag"), (2, "jitter")])
def test_scans_stamped_back_a_little_round_trip_in_their_order(tmp_path: Path, version: int, name: str) -> None:
    # A CARMEN log's stamps jitter back (Intel's 631 times, by up to 0.9 s; read_carmen keeps
    # them): the writer refused such a sequence, so Intel could not be made a bag.
    scans = scan_sequence(n=8)
    t0 = scans.timestamps[0]
    # One stamp ahead of both neighbours (scan 2), and two going back in turn (scans 5 and 6).
    scans.timestamps = t0 + np.array([0.0, 0.1, 0.9, 0.3, 0.4, 0.35, 0.2, 1.0])
    write_laserscan_bag(tmp_path / name, scans, version=version)
    with pytest.warns(RosbagWarning, match=r"3 scans on /scan are stamped earlier than the one before \(by up to "
                                           r"0.600 s\); kept in the bag's order"):
        back = read_laserscan_bag(tmp_path / name)
    np.testing.assert_allclose(back.timestamps - t0, scans.timestamps - t0, atol=1e-6)  # float64 of 1.3e9 s
    np.testing.assert_array_equal(back.ranges, scans.ranges)
    # Each scan's own pose, not one interpolated between its neighbours in the bag's order.
    np.testing.assert_allclose(back.odometry, scans.odometry, atol=1e-9)
    np.testing.assert_allclose(back.ground_truth, scans.ground_truth, atol=1e-9)


def test_laserscan_writer_checks(tmp_path: Path) -> None:
    scans = scan_sequence(n=3)
    with pytest.raises(ValueError, match="'.bag'"):
        write_laserscan_bag(tmp_path / "x", scans, version=1)
    with pytest.raises(ValueError, match="'.bag'"):
        write_laserscan_bag(tmp_path / "x.bag", scans, version=2)
    uneven = ScanSequence(scans.timestamps, scans.ranges[:, :3], [0.0, 0.1, 0.3], scans.odometry)
    with pytest.raises(ValueError, match="evenly spaced"):
        write_laserscan_bag(tmp_path / "x", uneven)
    back = scans.slice()
    back.timestamps = back.timestamps[0] + np.array([0.0, 1.2, 0.1])  # the reader refuses more than 1 s
    with pytest.raises(ValueError, match=r"scan 2 is stamped 1.100000 s earlier than one before it; at most 1 s"):
        write_laserscan_bag(tmp_path / "x", back)
    # What read_laserscan_bag refuses: scans that span no time.
    still = scans.slice()
    still.timestamps = np.full(3, still.timestamps[0])
    with pytest.raises(ValueError, match=r"all 3 scans are stamped .* s; read_laserscan_bag refuses scans that span "
                                         r"no time"):
        write_laserscan_bag(tmp_path / "x", still)
    assert list(tmp_path.iterdir()) == []
    # Stamps that go back may end where they began and still span time: written, not refused.
    there_and_back = scans.slice()
    there_and_back.timestamps = there_and_back.timestamps[0] + np.array([0.0, 0.5, 0.0])
    write_laserscan_bag(tmp_path / "back_again", there_and_back)
    # Readings of NaN or 0 m or less, no reading to a reader, are written as no echo (+inf): a
    # ScanSequence of nothing else reads back, as it did, as beams without an echo.
    blind = scans.slice()
    row = np.where(np.arange(blind.ranges.shape[1]) % 2 == 0, 0.0, np.nan)
    blind.ranges = np.tile(row, (len(blind), 1)).astype(np.float32)
    write_laserscan_bag(tmp_path / "blind", blind)
    assert np.isposinf(read_warned(tmp_path / "blind")[0].ranges).all()


@pytest.mark.parametrize(
    ("topics", "message"),
    [
        ({"scan_topic": "/odom"}, "scan_topic and odom_topic are both '/odom'"),
        ({"odom_topic": "/ground_truth"}, "odom_topic and ground_truth_topic are both '/ground_truth'"),
        ({"scan_topic": "/tf_static"}, "scan_topic and tf_static_topic are both '/tf_static'"),
    ],
)
def test_laserscan_writer_refuses_one_topic_for_two_roles(tmp_path: Path, topics: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"{re.escape(message)}: each needs a topic of its own"):
        write_laserscan_bag(tmp_path / "x", scan_sequence(n=3), **topics)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"scan": "/odom", "odometry": "/odom"}, "scan and odometry are both '/odom'"),
        ({"odometry": "/ground_truth"}, "ground_truth and odometry are both '/ground_truth'"),
        ({"scan": "/tf_static"}, "scan and tf_static are both '/tf_static'"),
        ({"tf_static": "/gt", "ground_truth": "/gt"}, "ground_truth and tf_static are both '/gt'"),
    ],
)
def test_laser_topics_refuse_one_topic_for_two_roles(given: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"{re.escape(message)}: each needs a topic of its own"):
        LaserTopics(**given)
    with pytest.raises(ValueError, match=re.escape(message)):
        LaserTopics.parse(",".join(f"{role}={topic}" for role, topic in given.items()))


def test_laser_topics_may_share_tf_where_it_carries_the_odometry_or_the_mounting() -> None:
    assert LaserTopics(odometry="/tf").odometry == "/tf"
    assert LaserTopics(tf_static="/tf").tf_static == "/tf"  # a ROS 1 bag's mounting repeated on /tf


def test_a_topic_for_ground_truth_the_scans_do_not_have_clashes_with_nothing(tmp_path: Path) -> None:
    scans = scan_sequence(n=3)
    scans.ground_truth = None  # no ground truth topic is written
    write_laserscan_bag(tmp_path / "x", scans, ground_truth_topic="/odom")
    assert read_laserscan_bag(tmp_path / "x").ground_truth is None


@pytest.mark.parametrize("field", ["odometry", "ground_truth"])
def test_laserscan_writer_refuses_poses_its_reader_would(tmp_path: Path, field: str) -> None:
    scans = scan_sequence(n=3)
    getattr(scans, field)[2, 1] = np.nan
    with pytest.raises(ValueError, match=rf"the scans' {field} pose 2 is not finite: \[[^,]+, nan, "):
        write_laserscan_bag(tmp_path / "x", scans)
    assert list(tmp_path.iterdir()) == []


LEVEL = (0.0, 0.0, math.sin(0.05), math.cos(0.05))  # yaw 0.1 rad
FLIPPED = (math.cos(0.05), math.sin(0.05), 0.0, 0.0)  # qz(0.1)·qx(π): upside down, yaw 0.1
PITCHED = (0.0, math.sin(0.1), 0.0, math.cos(0.1))  # pitch 0.2 rad, no yaw


def ros1_laser_bag(path: Path, *, tf=True, laser_q=LEVEL, extra_scan_topic=None) -> Path:
    """A ROS 1 bag as a robot would record it: odometry at 50 Hz moving along an analytic path
    (x = 0.5 t, y = -0.2 t, θ = 0.3 t, linear in t so interpolation is exact), scans at 10 Hz
    starting before the odometry, a tf tree base_link → laser_mount → /base_laser."""
    messages: list[tuple[str, str, object]] = []
    if tf:
        half = math.sin(0.25), math.cos(0.25)
        mount = ("base_link", "laser_mount", (0.2, 0.1, 0.3), (0.0, 0.0, *half))  # yaw 0.5
        laser = ("laser_mount", "base_laser", (0.05, 0.0, 0.0), laser_q)  # 0.05 m forward
        messages.append(("/tf_static", TF, tf_msg(NOETIC, [mount, laser])))
    events = []
    for k in range(51):  # odometry from 0.1 s to 1.1 s
        t = 0.1 + 0.02 * k
        events.append((t, "odom", (0.5 * t, -0.2 * t, 0.3 * t)))
    for k in range(13):  # scans 0.0 .. 1.2 s (at 0.05 + 0.1 k)
        events.append((0.05 + 0.1 * k, "scan", k))
    for t, kind, value in sorted(events, key=lambda e: e[0]):
        ns = 1000 * NS + round(t * NS)
        if kind == "odom":
            messages.append(("/odom", ODOM, odometry_msg(NOETIC, ns, value, "base_link")))
        else:
            ranges = [1.0 + 0.25 * value, math.nan, 0.05, 4.0, 4.5, -math.inf, math.inf, 0.1]
            messages.append(("/base_scan", SCAN, scan_msg(NOETIC, ns, ranges, frame="/base_laser")))
            if extra_scan_topic:
                messages.append((extra_scan_topic, SCAN, scan_msg(NOETIC, ns, ranges)))
    return write_raw(path, messages, ros1=True)


def test_ros1_laserscan_bag(tmp_path: Path) -> None:
    path = ros1_laser_bag(tmp_path / "robot.bag")
    with pytest.warns(RosbagWarning, match="dropped 3 of 13 scans on /base_scan"):
        scans = read_laserscan_bag(path)
    assert len(scans) == 10 and scans.n_beams == 8
    t = 0.15 + 0.1 * np.arange(10)
    np.testing.assert_allclose(scans.timestamps, 1000 + t, rtol=0, atol=1e-9)
    # Interpolated odometry between 50 Hz poses equals the analytic (linear) path.
    assert_poses(scans.odometry, np.column_stack([0.5 * t, -0.2 * t, 0.3 * t]), atol=1e-9)
    # Ranges: NaN, ±inf, below range_min (0.1), at range_max (4.0: many drivers' no-echo value)
    # and above it are no echo; range_min itself is a reading.
    expected = np.array([1.0, np.inf, np.inf, np.inf, np.inf, np.inf, np.inf, 0.1], np.float32)
    np.testing.assert_array_equal(scans.ranges[0, 1:], expected[1:])
    np.testing.assert_array_equal(scans.ranges[:, 0], np.float32(1.0 + 0.25 * np.arange(1, 11)))
    np.testing.assert_allclose(scans.angles, -1.0 + 0.5 * np.arange(8), rtol=0, atol=1e-7)
    assert scans.max_range == 4.0 and scans.ground_truth is None
    # base_link → laser_mount (0.2, 0.1, yaw 0.5) → base_laser (0.05 forward, yaw 0.1).
    expected_pose = [0.2 + 0.05 * math.cos(0.5), 0.1 + 0.05 * math.sin(0.5), 0.6]
    np.testing.assert_allclose(scans.sensor_pose, expected_pose, rtol=0, atol=1e-12)
    assert scans.remissions is None  # the scans carry no intensities


def yaw_q(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))


def tf_odometry_bag(path: Path, *, ros1: bool = True, children=("base_footprint",), static_topic="/tf_static",
                    shuffled: bool = False, odom_topic: bool = False, tf_type: str = TF) -> Path:
    """A bag as robots that publish their odometry only to tf record it: the transform
    /odom → each of `children` on /tf at 50 Hz along the analytic path of `ros1_laser_bag`
    (its first child's; the others' shifted by 1 m), the mounting base_footprint → base_link →
    laser (0.1 m forward, yaw 0.2) on `static_topic` (on /tf: repeated with every odometry
    message, as ROS 1's static_transform_publisher did), scans at 10 Hz. `shuffled`: the /tf
    messages out of stamp order in pairs, and each stamp published twice, the first time wrong.
    `odom_topic`: also a nav_msgs/Odometry /odom along a different path (0.1 t, 0, 0). `tf_type`:
    the message type of /tf and /tf_static."""
    store = NOETIC if ros1 else HUMBLE
    mounting = [("base_footprint", "base_link", (0.0, 0.0, 0.1), yaw_q(0.0)),
                ("base_link", "laser", (0.1, 0.0, 0.2), yaw_q(0.2))]
    messages: list[tuple[str, str, object]] = []
    if static_topic == "/tf_static":
        messages.append(("/tf_static", tf_type, tf_msg(store, mounting, msgtype=tf_type)))
    events = []
    for k in range(51):
        t = 0.1 + 0.02 * k
        ns = 1000 * NS + round(t * NS)
        moves = [("/odom", child, (0.5 * t + i, -0.2 * t, 0.0), yaw_q(0.3 * t)) for i, child in enumerate(children)]
        if shuffled:  # a wrong pose first, then the right one at the same stamp
            events.append((t - 1e-6, "tf", tf_msg(store, [(p, c, (9.0, 9.0, 0.0), q) for p, c, _, q in moves], ns,
                                                  tf_type)))
        events.append((t, "tf", tf_msg(store, moves + (mounting if static_topic == "/tf" else []), ns, tf_type)))
        if odom_topic:
            events.append((t, "odom", odometry_msg(store, ns, (0.1 * t, 0.0, 0.0), "base_footprint")))
    for k in range(13):
        events.append((0.05 + 0.1 * k, "scan", k))
    events.sort(key=lambda e: e[0])
    if shuffled:  # every two stamps' tf messages swapped (each stamp's in its order): out of order
        tf_at = [i for i, e in enumerate(events) if e[1] == "tf"]
        for a, b in zip(tf_at[0::4], tf_at[2::4]):
            events[a], events[b], events[a + 1], events[b + 1] = events[b], events[a], events[b + 1], events[a + 1]
    for t, kind, value in events:
        if kind == "tf":
            messages.append(("/tf", tf_type, value))
        elif kind == "odom":
            messages.append(("/odom", ODOM, value))
        else:
            ns = 1000 * NS + round(t * NS)
            messages.append(("/scan", SCAN, scan_msg(store, ns, [1.0 + 0.25 * value, 2.0, 3.0], frame="laser")))
    return write_raw(path, messages, ros1=ros1)


@pytest.mark.parametrize("ros1", [True, False])
def test_odometry_read_from_tf_where_the_bag_has_no_odometry_topic(tmp_path: Path, ros1: bool) -> None:
    # gmapping and slam_toolbox take the odometry from tf (odom → base); many robots record
    # nothing else. The transform's own stamps, interpolated to the scans.
    path = tf_odometry_bag(tmp_path / ("robot.bag" if ros1 else "robot"), ros1=ros1)
    scans, messages = read_warned(path)
    t = 0.15 + 0.1 * np.arange(10)
    np.testing.assert_allclose(scans.timestamps, 1000 + t, rtol=0, atol=1e-9)
    assert_poses(scans.odometry, np.column_stack([0.5 * t, -0.2 * t, 0.3 * t]), atol=1e-9)
    assert "odom → base_footprint on /tf" in scans.odometry_rule
    # base_footprint → base_link → laser: 0.1 m forward, yaw 0.2 (the heights dropped).
    np.testing.assert_allclose(scans.sensor_pose, [0.1, 0.0, 0.2], rtol=0, atol=1e-12)
    assert not any("static transform" in m for m in messages)


def test_tf_odometry_out_of_order_and_republished_is_sorted_and_the_last_kept(tmp_path: Path) -> None:
    scans, _ = read_warned(tf_odometry_bag(tmp_path / "robot.bag", shuffled=True))
    t = 0.15 + 0.1 * np.arange(10)
    assert_poses(scans.odometry, np.column_stack([0.5 * t, -0.2 * t, 0.3 * t]), atol=1e-9)


@pytest.mark.parametrize("tf_type", [TF, OLD_TF])
def test_mounting_repeated_on_tf_as_old_ros1_bags_have_it(tmp_path: Path, tf_type: str) -> None:
    scans, messages = read_warned(tf_odometry_bag(tmp_path / "robot.bag", static_topic="/tf", tf_type=tf_type))
    t = 0.15 + 0.1 * np.arange(10)
    assert_poses(scans.odometry, np.column_stack([0.5 * t, -0.2 * t, 0.3 * t]), atol=1e-9)
    np.testing.assert_allclose(scans.sensor_pose, [0.1, 0.0, 0.2], rtol=0, atol=1e-12)
    assert not any("static transform" in m for m in messages)


def test_tf_odometry_names_the_robot_frame_among_several_and_is_chosen_by_name(tmp_path: Path) -> None:
    path = tf_odometry_bag(tmp_path / "robot.bag", children=("base_footprint", "dock"))
    with pytest.raises(InputError) as info:
        read_laserscan_bag(path)
    message = str(info.value)
    assert "odom moves several frames (base_footprint, dock)" in message and "base_frame=FRAME" in message
    scans, _ = read_warned(path, topics=LaserTopics(base_frame="base_footprint"))
    t = 0.15 + 0.1 * np.arange(10)
    assert_poses(scans.odometry, np.column_stack([0.5 * t, -0.2 * t, 0.3 * t]), atol=1e-9)
    with pytest.raises(InputError, match=r"no transform odom → base_link .*odom → base_footprint, odom → dock"):
        read_laserscan_bag(path, topics=LaserTopics(base_frame="base_link"))
    with pytest.raises(InputError, match=r"no transform from the frame map .*odom_frame=FRAME"):
        read_laserscan_bag(path, topics=LaserTopics(odom_frame="map"))


def test_a_tf_odometry_transform_that_is_not_finite_is_named(tmp_path: Path) -> None:
    messages = [("/tf", TF, tf_msg(NOETIC, [("odom", "base_link", (k, math.nan if k == 2 else 0.0, 0.0), yaw_q(0))],
                                  k * NS)) for k in range(1, 4)]
    messages += [("/scan", SCAN, scan_msg(NOETIC, k * NS, [1.0, 2.0])) for k in range(1, 4)]
    path = write_raw(tmp_path / "nan.bag", messages, ros1=True)
    with pytest.raises(InputError, match=r"topic /tf: the transform odom → base_link stamped 2.000000000 s is not "
                                         r"finite \(position 2.0, nan"):
        read_laserscan_bag(path)


def test_tf_odometry_under_another_frame_is_pointed_at_and_slashed_names_are_frames(tmp_path: Path) -> None:
    # A PR2 publishes odom_combined → base_footprint; a user copies "/odom_combined" from rosbag info.
    messages = [("/tf", TF, tf_msg(NOETIC, [("/odom_combined", "/base_footprint", (0.1 * k, 0.0, 0.0), yaw_q(0))],
                                  k * NS)) for k in range(1, 5)]
    messages += [("/scan", SCAN, scan_msg(NOETIC, k * NS, [1.0, 2.0])) for k in range(1, 5)]
    path = write_raw(tmp_path / "pr2.bag", messages, ros1=True)
    scans, warned = read_warned(path)
    assert not scans.odometry_known
    assert any("may be the transform from odom_combined: name it with --laser-topics odom_frame=FRAME" in m
               for m in warned)
    scans, _ = read_warned(path, topics=LaserTopics(odom_frame="/odom_combined", base_frame="/base_footprint"))
    assert scans.odometry_known and "odom_combined → base_footprint" in scans.odometry_rule
    np.testing.assert_allclose(scans.odometry[:, 0], 0.1 * np.arange(1, 5), atol=1e-9)


def test_an_odometry_topic_wins_unless_tf_is_named(tmp_path: Path) -> None:
    path = tf_odometry_bag(tmp_path / "robot.bag", odom_topic=True)
    t = 0.15 + 0.1 * np.arange(10)
    scans, _ = read_warned(path)
    assert_poses(scans.odometry, np.column_stack([0.1 * t, 0 * t, 0 * t]), atol=1e-9)
    scans, _ = read_warned(path, topics=LaserTopics(odometry="/tf"))
    assert_poses(scans.odometry, np.column_stack([0.5 * t, -0.2 * t, 0.3 * t]), atol=1e-9)
    with pytest.raises(InputError, match=r"topic /scan has type sensor_msgs/msg/LaserScan, expected nav_msgs/msg/Odometry or"):
        read_laserscan_bag(path, topics=LaserTopics(odometry="/scan"))


def test_a_bag_without_any_odometry_reads_with_its_odometry_unknown(tmp_path: Path) -> None:
    # A lidar alone (Cartographer's backpack and Revo LDS bags): SLAM estimates the odometry
    # from the scans (omnitof.slam.scan_odometry); the reader says there is none.
    scans = [("/scan", SCAN, scan_msg(NOETIC, k * NS, [1.0, 2.0])) for k in range(1, 4)]
    for name, messages in (("bare.bag", scans),
                           ("static_tf_only.bag", [("/tf", TF, tf_msg(NOETIC, [("base_link", "laser", (0.1, 0, 0), yaw_q(0))]))] + scans)):
        read, _ = read_warned(write_raw(tmp_path / name, messages, ros1=True))
        assert len(read) == 3 and not read.odometry_known and not read.odometry.any()
        assert read.odometry_rule.startswith("none: the bag has no nav_msgs/msg/Odometry topic")
    np.testing.assert_allclose(read.sensor_pose, [0.1, 0.0, 0.0])  # the mounting from /tf all the same


def multi_echo_msg(store, ns: int, echoes, *, frame="horizontal_laser_link", angle_min=-1.0, inc=0.5):
    """A sensor_msgs/MultiEchoLaserScan; `echoes` is one list of echo ranges per beam."""
    t = store.types
    echo = t["sensor_msgs/msg/LaserEcho"]
    return t["sensor_msgs/msg/MultiEchoLaserScan"](
        header=header(store, ns, frame), angle_min=angle_min, angle_max=angle_min + inc * (len(echoes) - 1),
        angle_increment=inc, time_increment=0.0, scan_time=0.0, range_min=0.1, range_max=30.0,
        ranges=[echo(echoes=np.asarray(e, dtype=np.float32)) for e in echoes],
        intensities=[echo(echoes=np.asarray([100.0] * len(e), dtype=np.float32)) for e in echoes],
    )


@pytest.mark.parametrize("ros1", [True, False])
def test_a_backpack_bag_of_multi_echo_scans_without_odometry(tmp_path: Path, ros1: bool) -> None:
    # As Cartographer's backpack bags are: two MultiEchoLaserScan topics (a horizontal and a
    # vertical laser), no odometry. Each beam's first echo is its range; the horizontal laser is
    # named, the odometry is left to SLAM to estimate.
    store = NOETIC if ros1 else HUMBLE
    multi = "sensor_msgs/msg/MultiEchoLaserScan"
    messages = []
    for k in range(1, 4):
        beams = [[1.0 + k, 1.5 + k], [], [2.0, 9.0], [40.0]]  # the last beyond range_max: no echo
        messages.append(("/horizontal_laser_2d", multi, multi_echo_msg(store, k * NS, beams)))
        messages.append(("/vertical_laser_2d", multi, multi_echo_msg(store, k * NS, [[0.5]], frame="vertical_laser_link")))
    path = write_raw(tmp_path / ("backpack.bag" if ros1 else "backpack"), messages, ros1=ros1)
    with pytest.raises(InputError, match="several sensor_msgs/msg/LaserScan or sensor_msgs/msg/MultiEchoLaserScan "
                                         "topics: /horizontal_laser_2d, /vertical_laser_2d"):
        read_laserscan_bag(path)
    scans, _ = read_warned(path, topics=LaserTopics(scan="/horizontal_laser_2d"))
    assert len(scans) == 3 and not scans.odometry_known
    np.testing.assert_array_equal(scans.ranges, [[1.0 + k, np.inf, 2.0, np.inf] for k in range(1, 4)])
    np.testing.assert_allclose(scans.angles, [-1.0, -0.5, 0.0, 0.5])
    assert scans.remissions is None  # the empty beam has no first intensity either
    from omnitof.io.scans import is_tof_bag

    assert not is_tof_bag(path)


@pytest.mark.parametrize("version", [1, 2])
def test_laserscan_bag_with_odometry_on_tf_round_trips(tmp_path: Path, version: int) -> None:
    rng = np.random.default_rng(5)
    n = 12
    scans = ScanSequence(
        timestamps=10.0 + 0.1 * np.arange(n),
        ranges=rng.uniform(0.5, 5.0, (n, 9)).astype(np.float32),
        angles=np.linspace(-1.0, 1.0, 9),
        odometry=np.column_stack([0.3 * np.arange(n), np.sin(np.arange(n)), 0.2 * np.arange(n) - 1.0]),
        sensor_pose=np.array([0.2, -0.05, 0.1]),
        max_range=6.0,
    )
    path = tmp_path / ("tf.bag" if version == 1 else "tf")
    write_laserscan_bag(path, scans, version=version, odometry_on_tf=True)
    assert "nav_msgs/msg/Odometry" not in bag_message_types(path)
    back, _ = read_warned(path)
    assert_poses(back.odometry, scans.odometry, atol=1e-9)
    np.testing.assert_allclose(back.sensor_pose, scans.sensor_pose, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(back.ranges, scans.ranges)
    assert "on /tf" in back.odometry_rule


def test_upside_down_laser(tmp_path: Path) -> None:
    scans, messages = read_warned(ros1_laser_bag(tmp_path / "robot.bag", laser_q=FLIPPED))
    assert not any("tilted" in m for m in messages)  # upside down is handled, not a tilt
    # An upside-down laser's beams run clockwise: angle a in its frame is -a in the plane.
    np.testing.assert_allclose(scans.angles, -(-1.0 + 0.5 * np.arange(8)), rtol=0, atol=1e-7)
    np.testing.assert_allclose(scans.sensor_pose[2], 0.6, atol=1e-12)


def test_tilted_laser_warns(tmp_path: Path) -> None:
    scans, messages = read_warned(ros1_laser_bag(tmp_path / "robot.bag", laser_q=PITCHED))
    assert any("base_laser is tilted 11.5°" in m for m in messages)
    np.testing.assert_allclose(scans.sensor_pose[2], 0.5, atol=1e-12)
    np.testing.assert_allclose(scans.angles, -1.0 + 0.5 * np.arange(8), rtol=0, atol=1e-7)


def test_laser_without_tf(tmp_path: Path) -> None:
    scans, messages = read_warned(ros1_laser_bag(tmp_path / "robot.bag", tf=False))
    assert any("no static transform base_link → base_laser" in m for m in messages)
    np.testing.assert_array_equal(scans.sensor_pose, np.zeros(3))


def test_topic_auto_detection(tmp_path: Path) -> None:
    path = ros1_laser_bag(tmp_path / "two.bag", extra_scan_topic="/scan_rear")
    with pytest.raises(InputError) as info:
        read_laserscan_bag(path)
    message = str(info.value)
    assert str(path) in message and "/base_scan, /scan_rear" in message and "--laser-topics scan=TOPIC" in message
    assert len(read_warned(path, topics=LaserTopics(scan="/scan_rear"))[0]) == 10
    # The conventional name wins over others: /scan is in frame "laser", which has no tf.
    path = ros1_laser_bag(tmp_path / "conv.bag", extra_scan_topic="/scan")
    scans, messages = read_warned(path)
    assert any("no static transform base_link → laser on" in m for m in messages)
    np.testing.assert_array_equal(scans.sensor_pose, np.zeros(3))
    with pytest.raises(InputError, match="topic /nope .*missing"):
        read_laserscan_bag(path, topics=LaserTopics(odometry="/nope"))


def test_laserscan_errors(tmp_path: Path) -> None:
    store = HUMBLE
    odom = [("/odom", ODOM, odometry_msg(store, k * NS, (k, 0, 0))) for k in range(3)]
    no_odom = write_raw(tmp_path / "a", [("/scan", SCAN, scan_msg(store, NS, [1.0]))])
    assert not read_warned(no_odom)[0].odometry_known
    # A range_max of NaN or 0 in one message does not lose the run: that scan's readings are
    # bounded by the others' range_max (4 m), with a warning naming the first.
    no_range = write_raw(tmp_path / "b", odom + [
        ("/scan", SCAN, scan_msg(store, NS, [1.0, 2.0])),
        ("/scan", SCAN, scan_msg(store, NS + 1, [1.0, 5.0, 3.0], rmax=math.nan)),
        ("/scan", SCAN, scan_msg(store, NS + 2, [1.5, 4.5], rmax=0.0)),
    ])  # fmt: skip
    scans, messages = read_warned(no_range)
    assert any("2 scan(s) on /scan with a range_max of NaN, 0 or less (first at 1.000000001 s); their "
               "readings are taken up to the maximum range, 4 m" in m for m in messages)
    np.testing.assert_array_equal(scans.scan_ranges(1), np.float32([1.0, np.inf, 3.0]))
    np.testing.assert_array_equal(scans.scan_ranges(2), np.float32([1.5, np.inf]))
    assert scans.max_range == 4.0 and scans.max_range_rule == "LaserScan range_max (4 m, others unbounded)"
    backwards = write_raw(tmp_path / "c", odom + [
        ("/scan", SCAN, scan_msg(store, 2 * NS, [1.0])),
        ("/scan", SCAN, scan_msg(store, NS // 2, [1.0])),
    ])  # fmt: skip
    with pytest.raises(InputError, match="topic /scan: timestamps go backwards.*1.500000 s earlier; at most 1 s") as info:
        read_laserscan_bag(backwards)
    assert info.value.path == backwards
    # Stamps that jitter back less than a second are kept in the bag's order, as CARMEN's are.
    jitter = write_raw(tmp_path / "c2", odom + [
        ("/scan", SCAN, scan_msg(store, 3 * NS // 2, [1.0])),
        ("/scan", SCAN, scan_msg(store, 6 * NS // 5, [2.0])),
        ("/scan", SCAN, scan_msg(store, 2 * NS, [3.0])),
    ])  # fmt: skip
    with pytest.warns(RosbagWarning, match="1 scans on /scan are stamped earlier than the one before .by up to 0.300 s"):
        scans = read_laserscan_bag(jitter)
    np.testing.assert_allclose(scans.timestamps, [1.5, 1.2, 2.0])
    np.testing.assert_allclose(scans.ranges[:, 0], [1.0, 2.0, 3.0])
    np.testing.assert_allclose(scans.odometry[:, 0], [1.5, 1.2, 2.0])
    outside = write_raw(tmp_path / "d", odom + [
        ("/scan", SCAN, scan_msg(store, 5 * NS, [1.0])),
    ])  # fmt: skip
    with pytest.raises(InputError, match="topic /odom: no scan on /scan lies within"):
        read_laserscan_bag(outside)


@pytest.mark.parametrize("odometry_ns", [[0, 0], [NS, 2 * NS], []], ids=["odometry at 0", "odometry timed", "none"])
def test_scans_whose_stamps_were_left_unset_are_refused(tmp_path: Path, odometry_ns: list[int]) -> None:
    # A bag recorded with use_sim_time and no /clock: every header stamp 0. Before, with its
    # odometry at 0 too, its 3 scans read at one instant and SLAM mapped the first alone (exit 0).
    odom = [("/odom", ODOM, odometry_msg(HUMBLE, ns, (k, 0, 0))) for k, ns in enumerate(odometry_ns)]
    scans = [("/scan", SCAN, scan_msg(HUMBLE, 0, [1.0 + k, 2.0])) for k in range(3)]
    path = write_raw(tmp_path / "b", odom + scans)
    with pytest.raises(InputError) as info:
        read_laserscan_bag(path)
    assert str(info.value) == (f"{path}: topic /scan: the 3 scans span no time (every one is stamped 0.000000000 s): "
                               "their header stamps were left unset, as by a node with use_sim_time and no /clock; "
                               "record the bag with /clock published, or without use_sim_time")
    # One scan spans no time and needs none.
    assert len(read_warned(write_raw(tmp_path / "one", scans[:1]))[0]) == 1


@pytest.mark.parametrize("ranges, rmin, rmax, message", [
    ([0.0, 0.01, math.nan], 0.02, 4.0, "every one of the 9 readings of the 3 scans is NaN, or 0 m or less, or below "
                                       "the scans' range_min 0.02 m, which LaserScan takes for no reading: there is "
                                       "nothing to map"),
    ([1.0, 20.0, math.inf], 50.0, 30.0, "no reading of the 3 scans is an echo: 6 of the 9 are below the scans' "
                                        "range_min 50 m (above their range_max 30 m), which LaserScan takes for no "
                                        "reading, and the other 3 saw nothing within range_max: there is nothing to map"),
], ids=["no reading", "range_min above range_max"])
def test_a_bag_without_a_reading_says_what_its_readings_are(tmp_path: Path, ranges, rmin, rmax, message) -> None:
    # Such readings were reported as "every range is beyond the sensor's 4 m or missing".
    scans = [("/scan", SCAN, scan_msg(HUMBLE, k * NS, ranges, rmin=rmin, rmax=rmax)) for k in (1, 2, 3)]
    path = write_raw(tmp_path / "b", scans)
    with pytest.raises(InputError) as info:
        read_laserscan_bag(path)
    assert str(info.value) == f"{path}: topic /scan: {message}"
    # One echo among them is a bag to read: the rest are no echo.
    scans[1] = ("/scan", SCAN, scan_msg(HUMBLE, 2 * NS, [0.0, math.nan, 3.0], rmin=0.02, rmax=4.0))
    read = read_warned(write_raw(tmp_path / "one", scans))[0]
    assert np.isfinite(read.ranges).sum() == 1 and read.ranges[1, 2] == 3.0


def test_a_scan_recorded_twice_is_read_once(tmp_path: Path) -> None:
    # The same message twice (a bag recorded from two connections) is one scan; a second scan
    # with the same stamp but other readings is kept (omnitof.types.drop_repeated_scans).
    store = HUMBLE
    odom = [("/odom", ODOM, odometry_msg(store, k * NS, (k, 0, 0))) for k in range(4)]
    twice = scan_msg(store, NS, [1.0, 2.0])
    path = write_raw(tmp_path / "twice", odom + [
        ("/scan", SCAN, twice), ("/scan", SCAN, twice), ("/scan", SCAN, scan_msg(store, NS, [1.5, 2.0])),
        ("/scan", SCAN, scan_msg(store, 2 * NS, [1.0, 2.0])),
    ])  # fmt: skip
    scans, messages = read_warned(path)
    assert any("1 scans on /scan repeat the scan before them exactly" in m for m in messages)
    np.testing.assert_allclose(scans.timestamps, [1.0, 1.0, 2.0])
    np.testing.assert_allclose(scans.ranges[:, 0], [1.0, 1.5, 1.0])
    assert scans.time_order() == {"repeated_scans_dropped": 1, "equal_stamps": 1, "backward_steps": 0}


def test_default_storage_is_mcap() -> None:
    assert DEFAULT_STORAGE == "mcap"  # rosbags writes MCAP; sqlite3 stays available
