"""Odometry and its topics in ROS bags, as users get them wrong: an odometry spanning no time,
empty or equal frame names, named topics the bag lacks, odometry on another tf topic, a ground
truth declared but never published, a zero quaternion, and a hole in the odometry. For both
readers (ToF bags and LaserScan bags), which share `omnitof.io.rosbag.odometry`.

Bags are written with the module's writers where they can make the case, else message by
message with rosbags (as another tool would).
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest

from omnitof.errors import InputError
from omnitof.io.rosbag import (
    LaserTopics,
    RosbagWarning,
    ToFFrameStamped,
    ToFTopics,
    read_laserscan_bag,
    read_tof_bag,
    write_laserscan_bag,
    write_tof_bag,
)
from omnitof.scan.tof_input import ToFInputWarning, read_tof_scans
from omnitof.types import ScanSequence, Trajectory
from bag_messages import HUMBLE, NS, ODOM, SCAN, TF, odometry_msg, read_warned, scan_msg, tf_msg, write_raw


# --- bags ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def rig():
    """The default rig: its camera for the frames, its YAML form as the sidecar, so that
    `read_tof_scans` has a geometry without a calibration file."""
    from omnitof.sensor.design import default_rig

    return default_rig()


def tof_bag(path: Path, rig, times, odometry: Trajectory | None, **kwargs) -> Path:
    """A ToF bag of frames at `times` (a flat wall 2 m away in every pixel) with the rig as sidecar."""
    shape = rig.camera.shape
    frames = [ToFFrameStamped(t, np.full(shape, 2.0, np.float32), np.full(shape, 500.0, np.float32)) for t in times]
    write_tof_bag(path, frames, camera=rig.camera, odometry=odometry, sidecar=rig.to_dict(), **kwargs)
    return path


def tof_scans(path: Path, **kwargs):
    """read_tof_scans, with its warnings (the sidecar's "no --calibration" one left out)."""
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        scans = read_tof_scans(path, **kwargs).scans
    return scans, [str(w.message) for w in record if "no --calibration" not in str(w.message)]


def laser_scans(n: int, t0: float = 100.0, dt: float = 0.1, odometry: bool = True) -> ScanSequence:
    """n scans of 4 beams, the robot moving 1 m/s along +x."""
    t = t0 + dt * np.arange(n)
    return ScanSequence(
        timestamps=t, ranges=np.full((n, 4), 2.0, np.float32), angles=np.linspace(-1.0, 1.0, 4),
        odometry=np.column_stack([t - t0, np.zeros(n), np.zeros(n)]), sensor_pose=np.zeros(3), max_range=4.0,
        odometry_known=odometry,
    )


def scans_at(seconds) -> list:
    return [("/scan", SCAN, scan_msg(HUMBLE, round(s * NS), [2.0, 2.0, 2.0], inc=1.0)) for s in seconds]


# --- A: an odometry spanning no time -------------------------------------------------------


@pytest.mark.parametrize("on_tf", [False, True])
def test_a_tof_odometry_spanning_no_time_is_an_error_for_frames_at_other_times(tmp_path: Path, rig, on_tf: bool):
    times = 100.0 + 0.1 * np.arange(5)
    # One Odometry message; on tf, five transforms that all carry one stamp (stamps left unset).
    stamps = np.full(5, times[2]) if on_tf else times[2:3]
    odometry = Trajectory(stamps, np.column_stack([np.arange(len(stamps)), np.zeros((len(stamps), 2))]))
    path = tof_bag(tmp_path / "b", rig, times, odometry, odometry_on_tf=on_tf)
    with pytest.raises(InputError) as info:
        tof_scans(path)
    source = "the transform odom → base_link on /tf" if on_tf else "/odom"
    assert (f"the odometry ({source}) spans no time (every pose is stamped 100.200000000 s" in str(info.value)
            and "no pose for frame 0 at 100.000000000 s" in str(info.value))
    # A frame at the odometry's one stamp has its pose: a one-frame bag reads.
    one = tof_bag(tmp_path / "one", rig, times[2:3], odometry, odometry_on_tf=on_tf)
    scans, warned = tof_scans(one)
    assert len(scans) == 1 and scans.odometry[0, 0] == odometry.poses[-1, 0] and not warned


def test_a_laserscan_odometry_spanning_no_time_is_an_error(tmp_path: Path):
    one_message = write_raw(tmp_path / "odom", [("/odom", ODOM, odometry_msg(HUMBLE, 2 * NS, (0, 0, 0)))]
                            + scans_at([1, 2, 3]))
    with pytest.raises(InputError, match=r"the odometry \(topic /odom\) spans no time \(every pose is stamped "
                                         r"2\.000000000 s.*the scans on /scan at other times \(2 of 3\)"):
        read_laserscan_bag(one_message)
    same_stamp = write_raw(tmp_path / "tf", [
        ("/tf", TF, tf_msg(HUMBLE, [("odom", "base_link", (x, 0, 0), (0, 0, 0, 1))], 2 * NS)) for x in (0.0, 1.0)
    ] + scans_at([1, 2, 3]))
    with pytest.raises(InputError, match=r"the odometry \(topic /tf \(odom → base_link\)\) spans no time"):
        read_laserscan_bag(same_stamp)


# --- B: frame names ------------------------------------------------------------------------


@pytest.mark.parametrize("topics", [ToFTopics, LaserTopics])
def test_empty_or_equal_frame_names_are_refused_naming_the_roles(topics):
    with pytest.raises(ValueError, match=r"odom_frame='/' names no frame"):
        topics.parse("odom_frame=/")
    with pytest.raises(ValueError, match=r"base_frame='//' names no frame"):
        topics(base_frame="//")
    with pytest.raises(ValueError, match=r"odom_frame and base_frame are both 'odom'"):
        topics.parse("base_frame=/odom")
    assert topics.parse("odom_frame=/odom_combined,base_frame=/base_footprint").odom_frame == "odom_combined"


def test_a_transform_from_a_frame_to_itself_is_no_odometry(tmp_path: Path):
    # tf2 ignores a self transform: odom → odom moves nothing.
    path = write_raw(tmp_path / "b", [("/tf", TF, tf_msg(HUMBLE, [("odom", "odom", (k, 0, 0), (0, 0, 0, 1))], k * NS))
                                      for k in range(1, 4)] + scans_at([1, 2, 3]))
    scans, _ = read_warned(path)
    assert not scans.odometry_known and not scans.odometry.any()


# --- C: named topics that are missing, odometry on another tf topic ------------------------


def test_a_named_topic_the_bag_lacks_is_an_error_listing_its_topics(tmp_path: Path):
    times = 100.0 + 0.1 * np.arange(3)
    odometry = Trajectory(times, np.zeros((3, 3)))
    shape = (6, 8)
    from omnitof.sensor.camera import Camera

    camera = Camera(8, 6, 10.0, 11.0, 3.5, 2.5, (0.0,) * 5)
    frames = [ToFFrameStamped(t, np.full(shape, 2.0, np.float32), np.ones(shape, np.float32)) for t in times]
    tof = tmp_path / "tof"
    write_tof_bag(tof, frames, camera=camera, odometry=odometry)
    assert read_tof_bag(tof).ground_truth is None  # the default /ground_truth may be absent
    for role, kind in (("ground_truth", "nav_msgs/msg/Odometry"), ("tf", "tf2_msgs/msg/TFMessage or tf/msg/tfMessage"),
                       ("samples", "sensor_msgs/msg/Image")):
        with pytest.raises(InputError, match=rf"topic /nope \({kind}\) is missing; the bag has: .*/odom "):
            read_tof_bag(tof, topics=ToFTopics(**{role: "/nope"}))
    # The writer refuses an odometry from a frame to itself (the base frame it writes by default).
    with pytest.raises(ValueError, match="odom_frame and the base frame are both 'base_link'"):
        write_tof_bag(tmp_path / "same", frames, camera=camera, odometry=odometry, odometry_on_tf=True,
                      topics=ToFTopics(odom_frame="base_link"))
    assert not (tmp_path / "same").exists()
    laser = tmp_path / "laser"
    write_laserscan_bag(laser, laser_scans(3))
    assert read_warned(laser)[0].ground_truth is None
    for role in ("ground_truth", "tf", "tf_static"):
        with pytest.raises(InputError, match=r"topic /nope \(.*\) is missing; the bag has: .*/scan "):
            read_laserscan_bag(laser, topics=LaserTopics(**{role: "/nope"}))


def test_odometry_on_another_tf_topic_is_pointed_at(tmp_path: Path):
    times = 100.0 + 0.1 * np.arange(3)
    shape = (6, 8)
    from omnitof.sensor.camera import Camera

    camera = Camera(8, 6, 10.0, 11.0, 3.5, 2.5, (0.0,) * 5)
    frames = [ToFFrameStamped(t, np.full(shape, 2.0, np.float32), np.ones(shape, np.float32)) for t in times]
    odometry = Trajectory(times, np.column_stack([np.arange(3.0), np.zeros((3, 2))]))
    tof = tmp_path / "tof"
    write_tof_bag(tof, frames, camera=camera, odometry=odometry, odometry_on_tf=True, topics=ToFTopics(tf="/tf_odom"))
    with pytest.warns(RosbagWarning, match=r"may be the transform odom → base_link on /tf_odom: name it with "
                                           r"--tof-topics odometry=/tf_odom"):
        assert read_tof_bag(tof).odometry is None
    np.testing.assert_array_equal(read_tof_bag(tof, topics=ToFTopics(odometry="/tf_odom")).odometry.poses,
                                  odometry.poses)
    laser = tmp_path / "laser"
    write_laserscan_bag(laser, laser_scans(3), odometry_on_tf=True, tf_topic="/tf_odom")
    scans, warned = read_warned(laser)
    assert not scans.odometry_known
    assert any("on /tf_odom: name it with --laser-topics odometry=/tf_odom" in m for m in warned)
    scans, _ = read_warned(laser, topics=LaserTopics(odometry="/tf_odom"))
    np.testing.assert_allclose(scans.odometry[:, 0], [0.0, 0.1, 0.2], atol=1e-9)
    # A bag without odometry whose only other transforms are the mounting: no hint.
    bare = tmp_path / "bare"
    write_laserscan_bag(bare, laser_scans(3, odometry=False))
    scans, warned = read_warned(bare)
    assert not scans.odometry_known and not warned


# --- D: a ground truth declared but never published ----------------------------------------


def test_a_ground_truth_declared_but_never_published_is_left_out_unless_named(tmp_path: Path):
    odom = [("/odom", ODOM, odometry_msg(HUMBLE, k * NS, (k, 0, 0))) for k in (1, 2, 3)]
    path = write_raw(tmp_path / "b", odom + scans_at([1, 2, 3]), declared=[("/ground_truth", ODOM), ("/gt", ODOM)])
    scans, warned = read_warned(path)
    assert scans.ground_truth is None and len(scans) == 3
    assert all("no static transform" in m for m in warned)  # the bag has no mounting: nothing else
    np.testing.assert_allclose(scans.odometry[:, 0], [1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="topic /gt: has no message"):
        read_laserscan_bag(path, topics=LaserTopics(ground_truth="/gt"))


def test_a_tof_ground_truth_declared_but_never_published_is_left_out(tmp_path: Path):
    from rosbags.highlevel import AnyReader

    from omnitof.sensor.camera import Camera

    times = 100.0 + 0.1 * np.arange(3)
    camera = Camera(8, 6, 10.0, 11.0, 3.5, 2.5, (0.0,) * 5)
    frames = [ToFFrameStamped(t, np.full((6, 8), 2.0, np.float32), np.ones((6, 8), np.float32)) for t in times]
    written = write_tof_bag(tmp_path / "w", frames, camera=camera, odometry=Trajectory(times, np.zeros((3, 3))))
    assert written == 3
    with AnyReader([tmp_path / "w"]) as reader:  # the same messages, and a /ground_truth without any
        messages = [(c.topic, c.msgtype, reader.deserialize(raw, c.msgtype)) for c, _, raw in reader.messages()]
    path = write_raw(tmp_path / "b", messages, declared=[("/ground_truth", ODOM)])
    bag = read_tof_bag(path)
    assert bag.ground_truth is None and len(list(bag.frames())) == 3
    with pytest.raises(InputError, match="topic /truth: has no message"):
        read_tof_bag(write_raw(tmp_path / "named", messages, declared=[("/truth", ODOM)]),
                     topics=ToFTopics(ground_truth="/truth"))


# --- E: a zero quaternion ------------------------------------------------------------------


def test_a_zero_quaternion_is_said_to_be_zero(tmp_path: Path):
    zero = (0.0, 0.0, 0.0, 0.0)
    odom = write_raw(tmp_path / "odom", [
        ("/odom", ODOM, odometry_msg(HUMBLE, k * NS, (k, 0, 0), q=zero if k == 2 else None)) for k in (1, 2, 3)
    ] + scans_at([1, 2, 3]))
    with pytest.raises(InputError) as info:
        read_laserscan_bag(odom)
    assert "topic /odom: the pose stamped 2.000000000 s has a zero quaternion (length 0)" in str(info.value)
    assert "not finite" not in str(info.value)
    tf = write_raw(tmp_path / "tf", [("/tf", TF, tf_msg(HUMBLE, [("odom", "base_link", (k, 0, 0), zero if k == 2 else
                                                                   (0, 0, 0, 1))], k * NS)) for k in (1, 2, 3)]
                   + scans_at([1, 2, 3]))
    with pytest.raises(InputError, match=r"topic /tf: the transform odom → base_link stamped 2\.000000000 s has a "
                                         r"zero quaternion \(length 0\)"):
        read_laserscan_bag(tf)
    # Not finite stays not finite.
    nan = write_raw(tmp_path / "nan", [("/odom", ODOM, odometry_msg(HUMBLE, k * NS, (k, 0, 0), q=(0, 0, math.nan, 1)))
                                       for k in (1, 2)] + scans_at([1, 2]))
    with pytest.raises(InputError, match="stamped 1.000000000 s is not finite"):
        read_laserscan_bag(nan)


# --- F: a hole in the odometry -------------------------------------------------------------


def stale_odometry(start: float, end: float, rate: float = 50.0) -> Trajectory:
    """A stale pose at t = 0 (an unstamped first transform), then poses at `rate` Hz from
    `start` to `end`, moving 1 m/s along +x from x = 1."""
    t = np.concatenate([[0.0], np.arange(start, end + 1e-9, 1.0 / rate)])
    x = np.concatenate([[0.0], 1.0 + t[1:] - start])
    return Trajectory(t, np.column_stack([x, np.zeros((len(t), 2))]))


@pytest.mark.filterwarnings("ignore:.*no --calibration given")
def test_tof_frames_in_a_hole_of_the_odometry_are_dropped_not_interpolated(tmp_path: Path, rig):
    times = 100.0 + 0.1 * np.arange(10)
    odometry = stale_odometry(100.4, 101.0)
    path = tof_bag(tmp_path / "b", rig, times, odometry, odometry_on_tf=True)
    with pytest.warns(ToFInputWarning, match=r"dropped 4 frames outside the odometry's time span .* less its 1 "
                                             r"hole\(s\) without poses \(0\.000000000, 100\.400000000\) s .*frame 0; 6 kept"):
        scans = read_tof_scans(path).scans
    np.testing.assert_allclose(scans.timestamps, times[4:], atol=1e-9)
    np.testing.assert_allclose(scans.odometry[:, 0], 1.0 + times[4:] - 100.4, atol=1e-9)
    # The reader's own API says the same: no pose in the hole.
    bag = read_tof_bag(path)
    assert [f.odometry is None for f in bag.frames(samples=False)] == [True] * 4 + [False] * 6
    assert np.isnan(bag.odometry_at(times)[:4]).all() and not np.isnan(bag.odometry_at(times)[4:]).any()
    with pytest.raises(InputError, match=r"frame 0 at 100\.0+ s is outside the odometry's time span .* less its 1 hole"):
        bag.frame_odometry()


def test_laser_scans_in_a_hole_of_the_odometry_are_dropped_and_short_holes_kept(tmp_path: Path):
    scans = laser_scans(10)
    odometry = stale_odometry(100.4, 101.0)
    odom = [("/odom", ODOM, odometry_msg(HUMBLE, round(t * NS), (x, 0, 0)))
            for t, x in zip(odometry.timestamps, odometry.poses[:, 0])]
    stamps = list(scans.timestamps)
    path = write_raw(tmp_path / "b", odom + scans_at(stamps))
    read, warned = read_warned(path)
    np.testing.assert_allclose(read.timestamps, scans.timestamps[4:], atol=1e-9)
    np.testing.assert_allclose(read.odometry[:, 0], 1.0 + scans.timestamps[4:] - 100.4, atol=1e-9)
    assert any("dropped 4 of 10 scans on /scan" in m and "hole(s) without poses (0.000000000, 100.400000000)" in m
               for m in warned)
    # A hole of 0.8 s in an odometry at 50 Hz is under the 1 s floor: interpolated across.
    t = np.concatenate([100.0 + 0.02 * np.arange(5), 100.9 + 0.02 * np.arange(5)])
    short = write_raw(tmp_path / "short", [("/odom", ODOM, odometry_msg(HUMBLE, round(s * NS), (s - 100.0, 0, 0)))
                                           for s in t] + scans_at(stamps))
    read, warned = read_warned(short)
    assert len(read) == 10 and all("no static transform" in m for m in warned)
    np.testing.assert_allclose(read.odometry[:, 0], scans.timestamps - 100.0, atol=1e-9)
