"""Tests of omnitof.io.carmen: small logs written here, plus the bundled real logs if present."""

from __future__ import annotations

import bz2
import functools
import gzip
import math
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from omnitof.errors import ConfigError, InputError
from omnitof.geometry import compose, wrap_angle
from omnitof.io.carmen import CarmenWarning, old_format_angles, read_carmen
from omnitof.types import ScanSequence

DEG = math.pi / 180.0
HOST = "testhost"


# --------------------------------------------------------------------------------------------
# Builders of log lines


def _fmt(values) -> str:
    """Numbers as CARMEN writes them: counts as integers, the rest as decimals."""
    return " ".join(v if isinstance(v, str) else str(v) if isinstance(v, int) else repr(float(v))
                    for v in values)  # fmt: skip


def flaser(ranges, t, laser_pose=(0, 0, 0), odom=None, name="FLASER") -> str:
    odom = laser_pose if odom is None else odom
    return f"{name} " + _fmt([len(ranges), *ranges, *laser_pose, *odom, t, HOST, t - 100.0])


def odom(x, y, theta, t) -> str:
    return "ODOM " + _fmt([x, y, theta, 0.1, 0.0, 0.0, t, HOST, t - 100.0])


def config(start, res, max_range, n) -> list:
    return [0, start, res * n, res, max_range, 0.01, 0]


def robotlaser(ranges, remissions, t, laser_pose, robot_pose, start=-math.pi / 2, res=DEG,
               max_range=30.0, name="ROBOTLASER1") -> str:  # fmt: skip
    n = len(ranges)
    values = [*config(start, res, max_range, n), n, *ranges, len(remissions), *remissions,
              *laser_pose, *robot_pose, 0.2, 0.0, 0.5, 0.3, 0.0, t, HOST, t - 100.0]  # fmt: skip
    return f"{name} " + _fmt(values)


def rawlaser(ranges, t, start=-math.pi / 2, res=DEG, max_range=30.0, remissions=(),
             name="RAWLASER1") -> str:  # fmt: skip
    n = len(ranges)
    values = [*config(start, res, max_range, n), n, *ranges, len(remissions), *remissions,
              t, HOST, t - 100.0]  # fmt: skip
    return f"{name} " + _fmt(values)


def write(tmp_path: Path, lines: list[str], name: str = "log.clf", newline: str = "\n") -> Path:
    path = tmp_path / name
    path.write_bytes((newline.join(lines) + newline).encode())
    return path


HEADER = [
    "# CARMEN Logfile",
    "# message_name [message contents] ipc_timestamp ipc_hostname logger_timestamp",
]


def old_log() -> list[str]:
    """Three 4-beam FLASER scans, ODOMs and messages to ignore."""
    return [
        *HEADER,
        "PARAM robot_frontlaser_offset 0.0 nohost 0",
        "PARAM robot_use_laser on 1071078718.462369 merci 1071078718.462368",
        odom(0.0, 0.0, 0.0, 10.0),
        flaser([1.0, 2.5, 81.83, 0.0], 10.05),
        "SYNC tag 10.07 host 1.0",
        odom(0.1, 0.0, 0.01, 10.1),
        flaser([1.5, -1.0, 3.25, 79.5], 10.15, odom=(0.1, 0.0, 0.01), laser_pose=(0.1, 0.0, 0.01)),
        "TRUEPOS 0 0 0 0 0 0 10.16 host 1.0",
        "NMEA-GGA 1 2 3 N 4 E 1 5 1.0 10 20 30 40 0 10.17 host 1.0",
        flaser([0.5, 0.5, 0.5, 0.5], 10.15, odom=(0.2, 0.1, -3.1), laser_pose=(0.2, 0.1, -3.1)),
        flaser([9.0] * 6, 10.3, name="RLASER"),
    ]


def rejects(excinfo, path: Path, line: int, *words: str) -> None:
    """The InputError names the file and line, and its text contains `words`."""
    err = excinfo.value
    assert err.path == path and err.line == line
    text = str(err)
    assert path.name in text and f":{line}:" in text
    for word in words:
        assert word in text, (word, text)


# --------------------------------------------------------------------------------------------
# Old format


def test_old_format_values(tmp_path):
    path = write(tmp_path, old_log())
    log = read_carmen(path)
    scans = log.scans
    assert len(scans) == 3 and scans.n_beams == 4
    np.testing.assert_array_equal(scans.timestamps, [10.05, 10.15, 10.15])  # equal stamps allowed
    inf = np.inf
    expected = [[1.0, 2.5, inf, inf], [1.5, inf, 3.25, 79.5], [0.5] * 4]
    np.testing.assert_array_equal(scans.ranges, np.array(expected, dtype=np.float32))
    assert scans.ranges.dtype == np.float32
    # 4 beams over 180°, last beam of the sweep dropped: -90°, -45°, 0°, 45°.
    np.testing.assert_allclose(scans.angles, np.array([-90, -45, 0, 45]) * DEG, atol=1e-12)
    np.testing.assert_array_equal(scans.odometry, [[0, 0, 0], [0.1, 0, 0.01], [0.2, 0.1, -3.1]])
    np.testing.assert_array_equal(scans.sensor_pose, [0, 0, 0])
    assert scans.max_range == 80.0
    assert scans.remissions is None and scans.source == str(path)
    assert log.params == {"robot_frontlaser_offset": "0.0", "robot_use_laser": "on"}
    np.testing.assert_array_equal(log.odometry.timestamps, [10.0, 10.1])
    np.testing.assert_array_equal(log.odometry.poses, [[0, 0, 0], [0.1, 0, 0.01]])
    assert log.ignored_messages == {"NMEA-GGA": 1, "RLASER": 1, "SYNC": 1, "TRUEPOS": 1}
    assert log.bad_lines == 0 and log.time_reversals == 0


def test_old_format_angle_convention():
    # CARMEN's readlog: start -90°, 1° (180 beams) or 0.5° (360 beams); odd counts keep both ends.
    np.testing.assert_allclose(old_format_angles(180, 180.0), np.arange(-90, 90) * DEG)
    np.testing.assert_allclose(old_format_angles(360, 180.0), np.arange(-180, 180) * 0.5 * DEG)
    np.testing.assert_allclose(old_format_angles(181, 180.0), np.arange(-90, 91) * DEG)
    np.testing.assert_allclose(old_format_angles(5, 100.0), np.array([-50, -25, 0, 25, 50]) * DEG)


def test_fov_from_keyword_and_param(tmp_path):
    lines = [flaser([1.0, 1.0, 1.0], 1.0)]
    path = write(tmp_path, lines)
    np.testing.assert_allclose(read_carmen(path).scans.angles, np.array([-90, 0, 90]) * DEG)
    np.testing.assert_allclose(
        read_carmen(path, fov_deg=90.0).scans.angles, np.array([-45, 0, 45]) * DEG
    )
    path = write(tmp_path, ["PARAM laser_front_laser_fov 100 nohost 0", *lines])
    np.testing.assert_allclose(
        read_carmen(path, fov_deg=90.0).scans.angles, np.array([-50, 0, 50]) * DEG
    )


@pytest.mark.parametrize(
    "param, expected, rule",
    [
        ("PARAM robot_front_laser_max 50.0 1.0 merci 1.0", 50.0, "PARAM robot_front_laser_max = 50"),
        ("PARAM laser_front_laser_max_range 8.0 nohost 0", 8.0, "PARAM laser_front_laser_max_range = 8"),
        ("# no parameter", 80.0, "default 80 m (2 readings at or beyond it)"),
    ],
)
def test_old_format_max_range(tmp_path, param, expected, rule):
    path = write(tmp_path, [param, flaser([7.9, 8.0, 49.0, 50.0, 81.91, 80.0], 1.0)])
    scans = read_carmen(path).scans
    assert scans.max_range == expected and scans.max_range_rule == rule
    raw = np.array([7.9, 8.0, 49.0, 50.0, 81.91, 80.0])
    want = np.where(raw >= expected, np.inf, raw).astype(np.float32)
    np.testing.assert_array_equal(scans.ranges[0], want)


@pytest.mark.parametrize("readings, message", [
    ([0.0] * 6, "every one of the 12 readings of the 2 FLASER scans is 0 m, which is no reading: there is nothing "
                "to map"),
    ([-1.0, 0.0, -0.5, 0.0, 0.0, 0.0], "every one of the 12 readings of the 2 FLASER scans is 0 m or less (-1 to 0 "
                                       "m), which is no reading: there is nothing to map"),
    ([0.0, 0.0, 81.91, 0.0, 80.0, 0.0], "no reading of the 2 FLASER scans is an echo: 8 of the 12 are 0 m, which is "
                                        "no reading, and the other 4 lie at or beyond the maximum range 80 m: there "
                                        "is nothing to map"),
])
def test_a_log_without_a_reading_says_what_its_readings_are(tmp_path, readings, message):
    # Readings of 0 m or less were reported as "every range is beyond the sensor's 80 m or missing".
    path = write(tmp_path, [flaser(readings, 1.0), flaser(readings, 2.0)])
    with pytest.raises(InputError) as info:
        read_carmen(path)
    assert str(info.value) == f"{path}: {message}"
    # One echo among them is a log to read: the rest are no echo.
    scans = read_carmen(write(tmp_path, [flaser(readings, 1.0), flaser([*readings[:-1], 3.0], 2.0)])).scans
    assert np.isfinite(scans.ranges).sum() == 1 and scans.ranges[1, -1] == 3.0


def walls_log(tmp_path, *, code=None, share=0.03, seed=0, extra=()):
    """60 FLASER scans of 180 readings at 1 cm: walls anywhere in 0.5 … 49.99 m, the SICK code
    81.83 now and then, and (if given) the laser's own no-echo `code` in `share` of the beams."""
    rng = np.random.default_rng(seed)
    ranges = np.round(rng.uniform(0.5, 49.99, (60, 180)), 2)
    ranges[rng.random(ranges.shape) < 0.01] = 81.83
    if code is not None:
        ranges[rng.random(ranges.shape) < share] = code
    lines = [*extra, *(flaser(list(r), 10.0 + 0.1 * i) for i, r in enumerate(ranges))]
    return write(tmp_path, lines), ranges


@pytest.mark.parametrize("code, shown", [(50.0, "50.00"), (50.005, "50.005")])
def test_a_repeated_top_value_is_the_lasers_no_echo(tmp_path, code, shown):
    # A code with more digits than centimetres is printed with them (0.001 m read "0.00 m").
    path, raw = walls_log(tmp_path, code=code)
    count = int(np.sum(raw == code))
    with pytest.warns(CarmenWarning, match=f"{count} readings of exactly {re.escape(shown)} m"):
        scans = read_carmen(path).scans
    assert scans.max_range == code
    assert scans.max_range_rule == f"repeated top value {shown} m ({count} readings)"
    walls = raw < code
    np.testing.assert_array_equal(scans.ranges[walls], raw[walls].astype(np.float32))  # kept
    assert np.isinf(scans.ranges[~walls]).all()  # the code and SICK's 81.83


@pytest.mark.parametrize("code, share", [(None, 0.0), (50.0, 0.002), (3.0, 0.2)])
def test_no_repeated_top_value_drops_nothing(tmp_path, code, share):
    # No code; one too rare to be a code (0.2 %, 20 readings); a value that repeats but is
    # not the top one (a wall the robot stared at).
    path, raw = walls_log(tmp_path, code=code, share=share)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = read_carmen(path).scans
    assert scans.max_range == 80.0
    assert scans.max_range_rule == f"default 80 m ({int(np.sum(raw >= 80))} readings at or beyond it)"
    walls = raw < 80.0
    np.testing.assert_array_equal(scans.ranges[walls], raw[walls].astype(np.float32))


def test_a_param_wins_over_a_repeated_top_value(tmp_path):
    path, raw = walls_log(tmp_path, code=50.0, extra=["PARAM robot_front_laser_max 81.0 nohost 0"])
    scans = read_carmen(path).scans
    assert scans.max_range == 81.0 and scans.max_range_rule == "PARAM robot_front_laser_max = 81"
    assert np.sum(np.isfinite(scans.ranges)) == np.sum(raw < 81.0)


def test_sensor_pose_from_params(tmp_path):
    params = [
        "PARAM robot_frontlaser_offset 0.25 nohost 0",
        "PARAM robot_frontlaser_side_offset -0.05 nohost 0",
        "PARAM robot_frontlaser_angular_offset 0.1 nohost 0",
    ]
    path = write(tmp_path, [*params, flaser([1.0, 2.0], 1.0, laser_pose=(3, 4, 0.5))])
    np.testing.assert_allclose(read_carmen(path).scans.sensor_pose, [0.25, -0.05, 0.1])
    path = write(tmp_path, [params[0], flaser([1.0, 2.0], 1.0)])  # missing ones are zero
    np.testing.assert_allclose(read_carmen(path).scans.sensor_pose, [0.25, 0.0, 0.0])


def test_rear_sensor_pose_from_params(tmp_path):
    scan = flaser([1.0, 2.0], 1.0, name="RLASER")
    path = write(tmp_path, ["PARAM robot_rearlaser_offset 0.2 nohost 0", scan])
    # Older CARMEN: the rear laser faces backwards, its offset measured along its heading.
    np.testing.assert_allclose(read_carmen(path, laser="rear").scans.sensor_pose, [-0.2, 0, np.pi])
    path = write(tmp_path, [
        "PARAM robot_rearlaser_offset -0.3 nohost 0",
        "PARAM robot_rearlaser_angular_offset 3.0 nohost 0",
        scan,
    ])  # fmt: skip
    np.testing.assert_allclose(read_carmen(path, laser="rear").scans.sensor_pose, [-0.3, 0, 3.0])


def _offset_scans(offset=(-0.04, 0.005, 0.0), turn_at_second=0.0):
    """FLASER lines whose laser pose is robot ⊕ offset, the robot turned by 90° and moving."""
    robots = np.array([[1.0, 2.0, math.pi / 2], [1.0, 2.5, math.pi / 2], [0.5, 2.5, math.pi]])
    lines = []
    for i, robot in enumerate(robots):
        mount = np.array(offset) + (0, 0, turn_at_second if i == 1 else 0.0)
        laser = compose(robot, mount)
        lines.append(flaser([1.0, 2.0], 1.0 + i, laser_pose=tuple(laser), odom=tuple(robot)))
    return robots, lines


def test_sensor_pose_from_messages(tmp_path):
    robots, lines = _offset_scans()
    path = write(tmp_path, ["PARAM robot_frontlaser_offset -0.04 nohost 0", *lines])
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the side offset is within 1 cm of the PARAM's zero
        log = read_carmen(path)
    np.testing.assert_allclose(log.scans.sensor_pose, [-0.04, 0.005, 0.0], atol=1e-12)
    np.testing.assert_array_equal(log.scans.odometry, robots)


def test_sensor_pose_params_disagree_warns(tmp_path):
    _, lines = _offset_scans()
    path = write(tmp_path, ["PARAM robot_frontlaser_offset 0.3 nohost 0", *lines])
    with pytest.warns(CarmenWarning, match="using the messages"):
        log = read_carmen(path)
    np.testing.assert_allclose(log.scans.sensor_pose, [-0.04, 0.005, 0.0], atol=1e-12)


def test_laser_poses_that_are_no_mount_are_left_out(tmp_path):
    # A laser pose turned by 1° at the second scan is no fixed mount: the scans and the odometry
    # are read, the mount comes from the PARAMs (else none), and a warning says where.
    robots, lines = _offset_scans(turn_at_second=1.0 * DEG)
    with pytest.warns(CarmenWarning, match=r"no fixed mount.*first scan \(line 1\).*at line 2.*mount is none"):
        log = read_carmen(write(tmp_path, lines))
    np.testing.assert_array_equal(log.scans.sensor_pose, [0.0, 0.0, 0.0])
    np.testing.assert_array_equal(log.scans.odometry, robots)
    with pytest.warns(CarmenWarning, match=r"mount is the PARAMs' \(x -0.0400 m"):
        log = read_carmen(write(tmp_path, ["PARAM robot_frontlaser_offset -0.04 nohost 0", *lines]))
    np.testing.assert_allclose(log.scans.sensor_pose, [-0.04, 0.0, 0.0])


def test_a_glitch_in_the_laser_poses_keeps_the_mount(tmp_path):
    # One scan of twenty whose laser pose is off by 30 cm (a logger's glitch) does not make the
    # mount a corrected log's trajectory: the median offset is the mount, and a warning names
    # the line.
    mount = np.array([0.12, -0.03, 0.05])
    t = np.arange(20) * 0.1
    robots = np.column_stack([0.5 * t, 0.2 * t, wrap_angle(3.0 + 0.3 * t)])
    lasers = compose(robots, mount)
    lasers[7] = compose(robots[7], mount + (0.3, 0.0, 0.0))
    lines = [flaser([1.0, 2.0], 10.0 + t[k], laser_pose=tuple(lasers[k]), odom=tuple(robots[k])) for k in range(20)]
    with pytest.warns(CarmenWarning, match=r"1 of 20 FLASER laser poses depart .*\(x 0.1200 m.*first at line 8 at \(x 0.4200 m"):
        log = read_carmen(write(tmp_path, lines))
    np.testing.assert_allclose(log.scans.sensor_pose, mount, atol=1e-6)
    np.testing.assert_array_equal(log.scans.odometry, robots)


@pytest.mark.parametrize("departing", [0, 2])
def test_a_mount_that_wavers_within_tolerance_or_departs_in_a_tenth_of_the_scans_is_kept(tmp_path, departing):
    # Offsets that drift by 1.5 cm over the log all lie within 1 cm of their median: the median
    # is the mount, with no warning. Two scans of twenty (exactly 10 %) off by 30 cm still leave
    # a mount, with a warning.
    t = np.arange(20) * 0.1
    robots = np.column_stack([0.5 * t, 0.2 * t, wrap_angle(3.0 + 0.3 * t)])
    mounts = np.column_stack([np.linspace(0.1, 0.115, 20), np.zeros(20), np.zeros(20)])
    mounts[:departing, 0] += 0.3
    lasers = np.array([compose(robots[k], mounts[k]) for k in range(20)])
    lines = [flaser([1.0, 2.0], 10.0 + t[k], laser_pose=tuple(lasers[k]), odom=tuple(robots[k])) for k in range(20)]
    with warnings.catch_warnings(record=True) as record:
        warnings.simplefilter("always")
        log = read_carmen(write(tmp_path, lines))
    messages = [str(w.message) for w in record]
    np.testing.assert_allclose(log.scans.sensor_pose, [np.median(mounts[:, 0]), 0.0, 0.0], atol=1e-6)
    if departing:
        assert len(messages) == 1 and f"{departing} of 20 FLASER laser poses depart" in messages[0]
    else:
        assert messages == []


def test_a_corrected_log_is_read_with_its_odometry(tmp_path):
    # GMapping's .gfs.log: the laser pose fields hold the SLAM solution, which drifts away from
    # the raw odometry beside it by metres over the log.
    t = np.arange(200) * 0.1
    odometry = np.column_stack([0.5 * t, 0.1 * np.sin(t), wrap_angle(0.2 * t)])
    corrected = odometry + np.column_stack([0.02 * t, -0.01 * t, 0.004 * t])
    lines = [flaser([1.0, 2.0, 3.0 + 0.001 * k], 10.0 + t[k], laser_pose=tuple(corrected[k]), odom=tuple(odometry[k]))
             for k in range(len(t))]
    with pytest.warns(CarmenWarning, match=r"no fixed mount.*at line 200 .*GMapping's \.gfs\.log"):
        log = read_carmen(write(tmp_path, lines))
    np.testing.assert_allclose(log.scans.odometry, odometry, atol=1e-12)
    assert len(log.scans) == 200 and np.array_equal(log.scans.sensor_pose, np.zeros(3))


# --------------------------------------------------------------------------------------------
# New format


def test_robotlaser_with_remissions(tmp_path):
    robot_pose = (1.0, 2.0, 0.5)
    laser_pose = tuple(compose(np.array(robot_pose), np.array([0.2, 0.0, 0.0])))
    start, res = -0.75, 0.5
    lines = [
        *HEADER,
        robotlaser([1.0, 29.99, 30.0, -0.5], [10, 20, 30, 40], 5.0, laser_pose, robot_pose,
                   start=start, res=res),
        robotlaser([2.0, 2.0, 2.0, 2.0], [1, 2, 3, 4.5], 5.2, laser_pose, robot_pose,
                   start=start, res=res),
    ]  # fmt: skip
    log = read_carmen(write(tmp_path, lines))
    scans = log.scans
    np.testing.assert_array_equal(scans.timestamps, [5.0, 5.2])
    np.testing.assert_allclose(scans.angles, [-0.75, -0.25, 0.25, 0.75])
    np.testing.assert_array_equal(
        scans.ranges[0], np.array([1.0, 29.99, np.inf, np.inf], dtype=np.float32)
    )
    assert scans.max_range == 30.0
    np.testing.assert_array_equal(scans.remissions, [[10, 20, 30, 40], [1, 2, 3, 4.5]])
    assert scans.remissions.dtype == np.float32
    np.testing.assert_array_equal(scans.odometry, [robot_pose, robot_pose])
    # 0.2 m along the robot's heading.
    np.testing.assert_allclose(scans.sensor_pose, [0.2, 0.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("start, res", [(1e308, DEG), (-math.pi / 2, 1e300), (7.0, DEG)])
def test_beam_angles_beyond_a_turn_are_refused(tmp_path, start, res):
    lines = [robotlaser([1.0, 2.0], [], 1.0, (0, 0, 0), (0, 0, 0)),
             robotlaser([1.0, 2.0], [], 1.1, (0, 0, 0), (0, 0, 0), start=start, res=res)]
    with pytest.raises(InputError, match=r"start_angle .* put the beams at .* within ±2π") as excinfo:
        read_carmen(write(tmp_path, lines))
    assert excinfo.value.line == 2


@pytest.mark.parametrize("res", [0.0, 1e-300, -1e-9])
def test_a_zero_angular_resolution_is_refused(tmp_path, res):
    # Every beam at one angle: the scans would draw a single ray and the filter weigh nonsense.
    lines = [robotlaser([1.0, 2.0, 3.0], [], 1.0, (0, 0, 0), (0, 0, 0), res=res)]
    with pytest.raises(InputError, match=r"angular_resolution is '.*': it would put all 3 beams") as excinfo:
        read_carmen(write(tmp_path, lines))
    assert excinfo.value.line == 1


@pytest.mark.parametrize(("lines", "line", "words"), [
    # A laser 1000 km from the robot (an offset in another unit, a broken logger): the map's
    # cells cannot hold its end points, and the core refused them mid-run with a traceback.
    (["PARAM robot_frontlaser_offset 1e9 nohost 0", flaser([1.0, 2.0], 1.0)], 1,
     ["PARAM robot_frontlaser_offset puts the front laser 1e+09 m", "within 100 m"]),
    (["PARAM robot_frontlaser_side_offset -150 nohost 0", flaser([1.0, 2.0], 1.0)], 1,
     ["PARAM robot_frontlaser_side_offset puts the front laser 150 m"]),
    ([flaser([1.0, 2.0], 1.0, laser_pose=(500.0, 0, 0), odom=(0, 0, 0)),
      flaser([1.0, 2.0], 2.0, laser_pose=(501.0, 0, 0), odom=(1.0, 0, 0))], 1,
     ["FLASER laser poses lie 500 m from the robot poses"]),
    # Poses beyond a million kilometres (the trajectory files hold no more).
    ([flaser([1.0, 2.0], 1.0, laser_pose=(1e300, 0, 0), odom=(0, 0, 0))], 1, ["laser_x, laser_y = 1e+300, 0 m"]),
    ([odom(0.0, 2e9, 0.0, 1.0), rawlaser([1.0, 2.0], 1.1)], 1, ["x, y = 0, 2e+09 m lie beyond ±1e+09 m"]),
    ([robotlaser([1.0, 2.0], [], 1.0, (0, 0, 0), (-3e9, 0, 0))], 1, ["robot_x, robot_y = -3e+09, 0 m"]),
    # Headings beyond a million radians: wrapped, 1e300 rad was read as -138.55°, with a warning.
    ([flaser([1.0, 2.0], 1.0, laser_pose=(0, 0, 1e300), odom=(0, 0, 0)), flaser([1.0, 2.0], 1.1)], 1,
     ["laser_theta = 1e+300 rad lies beyond ±1e+06 rad"]),
    ([flaser([1.0, 2.0], 1.0), flaser([1.0, 2.0], 1.1, laser_pose=(0, 0, 0), odom=(0, 0, -2e6))], 2,
     ["odom_theta = -2e+06 rad lies beyond ±1e+06 rad"]),
    ([odom(0.0, 0.0, 1e300, 1.0), rawlaser([1.0, 2.0], 1.1)], 1, ["theta = 1e+300 rad lies beyond ±1e+06 rad"]),
    ([robotlaser([1.0, 2.0], [], 1.0, (0, 0, 1e300), (0, 0, 0))], 1, ["laser_theta = 1e+300 rad"]),
    ([robotlaser([1.0, 2.0], [], 1.0, (0, 0, 0), (0, 0, 1e300))], 1, ["robot_theta = 1e+300 rad"]),
    (["PARAM robot_frontlaser_angular_offset 1e300 nohost 0", flaser([1.0, 2.0], 1.0)], 1,
     ["PARAM robot_frontlaser_angular_offset is 1e+300 rad, beyond ±1e+06 rad"]),
])
def test_a_laser_far_from_the_robot_or_poses_beyond_a_million_km_or_radians_are_refused(tmp_path, lines, line, words):
    path = write(tmp_path, lines)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, line, *words)


def test_unwrapped_headings_within_a_million_radians_are_read(tmp_path):
    # Loggers that add up the turns (159 154 of them here): kept as logged, as the odometry is.
    theta = 999_999.5
    lines = [flaser([1.0, 2.0], 1.0, laser_pose=(0, 0, theta)), flaser([1.0, 2.0], 1.1, laser_pose=(0, 0, -theta))]
    scans = read_carmen(write(tmp_path, lines)).scans
    np.testing.assert_array_equal(scans.odometry[:, 2], [theta, -theta])


def test_a_reading_that_rounds_to_the_maximum_in_float32_is_no_echo(tmp_path):
    line = robotlaser([29.9999999, 29.99, 1.0], [], 1.0, (0, 0, 0), (0, 0, 0), max_range=30.0)
    ranges = read_carmen(write(tmp_path, [line])).scans.ranges
    np.testing.assert_array_equal(ranges, np.array([[np.inf, 29.99, 1.0]], np.float32))


def test_ranges_too_small_for_float32_are_no_reading(tmp_path):
    # 1e-50 m is above 0 but rounds to 0 in float32, the ScanSequence's dtype: no echo, not 0.
    lines = [flaser([1.0, 1e-50, -0.0, 2.0], 1.0), flaser([1.0, 2.0, 3.0, 1e-30], 1.1)]
    ranges = read_carmen(write(tmp_path, lines)).scans.ranges
    np.testing.assert_array_equal(ranges, np.array([[1.0, np.inf, np.inf, 2.0], [1.0, 2.0, 3.0, 1e-30]], np.float32))


def test_robotlaser_remission_count_differs(tmp_path):
    line = robotlaser([1.0, 2.0, 3.0], [5.0], 1.0, (0, 0, 0), (0, 0, 0))
    assert read_carmen(write(tmp_path, [line])).scans.remissions is None


def test_rawlaser_pose_from_odometry(tmp_path):
    lines = [
        "PARAM robot_frontlaser_offset 0.1 nohost 0",
        odom(0.0, 0.0, 3.0, 10.0),
        rawlaser([1.0, 2.0], 10.0, start=-0.1, res=0.2, remissions=(7.0, 8.0)),
        odom(2.0, 4.0, -2.9, 12.0),  # +0.3832 rad the short way round
        rawlaser([3.0, 31.0], 11.0, start=-0.1, res=0.2, remissions=(7.0, 8.0)),
        rawlaser([3.0, 4.0], 11.5, start=-0.1, res=0.2, remissions=(7.0, 8.0)),
        odom(2.0, 4.0, -2.9, 12.0),
    ]
    scans = read_carmen(write(tmp_path, lines)).scans
    step = 2 * math.pi - 5.9
    theta_mid = 3.0 + step / 2 - 2 * math.pi
    theta_3q = 3.0 + 0.75 * step - 2 * math.pi
    np.testing.assert_allclose(
        scans.odometry, [[0, 0, 3.0], [1.0, 2.0, theta_mid], [1.5, 3.0, theta_3q]], atol=1e-12
    )
    np.testing.assert_allclose(scans.angles, [-0.1, 0.1])
    np.testing.assert_array_equal(scans.ranges[1], [3.0, np.inf])
    np.testing.assert_array_equal(scans.remissions, [[7, 8]] * 3)
    np.testing.assert_allclose(scans.sensor_pose, [0.1, 0, 0])


def test_rawlaser_outside_odometry(tmp_path):
    lines = [odom(0, 0, 0, 10.0), odom(1, 0, 0, 11.0), rawlaser([1.0], 10.5), rawlaser([1.0], 11.5)]
    path = write(tmp_path, lines)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 4, "outside the odometry's time span")


def test_rawlaser_odometry_going_backwards(tmp_path):
    lines = [odom(0, 0, 0, 10.0), odom(1, 0, 0, 12.0), odom(2, 0, 0, 11.0), rawlaser([1.0], 10.5)]
    path = write(tmp_path, lines)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 3, "ODOM timestamps go backwards")


def test_rawlaser_without_odometry(tmp_path):
    path = write(tmp_path, [rawlaser([1.0], 10.5)])
    with pytest.raises(InputError, match="no ODOM message"):
        read_carmen(path)


def test_robotlaser_preferred_to_rawlaser(tmp_path):
    lines = [
        rawlaser([9.0, 9.0], 1.0),
        robotlaser([1.0, 2.0], [], 1.0, (0, 0, 0), (0, 0, 0)),
        robotlaser([3.0, 4.0], [], 2.0, (0, 0, 0), (0, 0, 0), name="ROBOTLASER2"),
    ]
    path = write(tmp_path, lines)
    log = read_carmen(path)
    np.testing.assert_array_equal(log.scans.ranges, [[1.0, 2.0]])
    assert log.ignored_messages == {"RAWLASER1": 1, "ROBOTLASER2": 1}
    rear = read_carmen(path, laser="rear")
    np.testing.assert_array_equal(rear.scans.ranges, [[3.0, 4.0]])
    assert rear.ignored_messages == {"RAWLASER1": 1, "ROBOTLASER1": 1}


def test_rear_laser_old_format(tmp_path):
    log = read_carmen(write(tmp_path, old_log()), laser="rear")
    np.testing.assert_array_equal(log.scans.ranges, np.full((1, 6), 9.0, dtype=np.float32))
    assert log.ignored_messages["FLASER"] == 3


def test_old_and_new_format_together(tmp_path):
    lines = [flaser([1.0, 2.0], 1.0), robotlaser([1.0, 2.0], [], 1.0, (0, 0, 0), (0, 0, 0))]
    path = write(tmp_path, lines)
    with pytest.raises(InputError, match=r"FLASER \(first at line 1\) and as ROBOTLASER1"):
        read_carmen(path)


# --------------------------------------------------------------------------------------------
# Files


@pytest.mark.parametrize("compress", [gzip.compress, bz2.compress])
@pytest.mark.parametrize("name", ["log.clf", "log.clf.gz", "log.clf.bz2"])
def test_compressed_by_magic_bytes(tmp_path, compress, name):
    text = "\n".join(old_log()) + "\n"
    path = tmp_path / name
    path.write_bytes(compress(text.encode()))
    log = read_carmen(path)
    assert len(log.scans) == 3
    np.testing.assert_array_equal(log.scans.ranges[2], [0.5] * 4)


def test_plain_file_with_gz_suffix(tmp_path):
    assert len(read_carmen(write(tmp_path, old_log(), name="log.gz")).scans) == 3


def test_crlf_and_trailing_whitespace(tmp_path):
    lines = [line + " \t " for line in old_log()]
    log = read_carmen(write(tmp_path, lines, newline="\r\n"))
    assert len(log.scans) == 3 and log.params["robot_use_laser"] == "on"
    np.testing.assert_array_equal(log.scans.timestamps, [10.05, 10.15, 10.15])


def test_a_byte_order_mark_before_the_first_message(tmp_path):
    # Some Windows editors write one; it sits before the first message, not in a comment.
    path = tmp_path / "bom.clf"
    lines = [line for line in old_log() if not line.startswith("#")]
    path.write_bytes(b"\xef\xbb\xbf" + ("\r\n".join(lines) + "\r\n").encode())
    log = read_carmen(path)
    assert len(log.scans) == 3 and log.params["robot_use_laser"] == "on"


# --------------------------------------------------------------------------------------------
# Errors


def _with_line(tmp_path, bad: str, position: int = 3) -> tuple[Path, int]:
    """old_log() with `bad` inserted as line `position` (1-based)."""
    lines = old_log()
    lines.insert(position - 1, bad)
    return write(tmp_path, lines), position


@pytest.mark.parametrize(
    "bad, words",
    [
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 4 ", " 6 ", 1),
         ["FLASER declares 6 ranges but 13 values follow the count",
          "expected 6 ranges + 6 pose values + ipc_timestamp ipc_hostname logger_timestamp"]),
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 4.0 ", " x4 ", 1),
         ["range 4 of 4 is 'x4', not a finite decimal number"]),
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 3.0 ", " nan ", 1),
         ["range 3 of 4 is 'nan'"]),
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 3.0 ", " inf ", 1),
         ["range 3 of 4 is 'inf'"]),
        ("FLASER 4 1 2 3 4 0 0 0 0 0 0", ["declares 4 ranges but 10 values follow"]),
        ("FLASER four 1 2 3 4 0 0 0 0 0 0 1.0 h 1.0", ["num_readings is 'four'"]),
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 11.0 ", " t ", 1),
         ["ipc_timestamp is 't'"]),
        # float() and numpy read "1_0" as 10 and Arabic-Indic or full-width digits as digits.
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 2.0 ", " 1_0 ", 1),
         ["range 2 of 4 is '1_0', not a finite decimal number"]),
        (flaser([1.0] * 40, 11.0).replace(" 1.0 1.0 1.0 ", " 1.0 1.0 1_0 ", 1),
         ["range 3 of 40 is '1_0'"]),
        (flaser([1.0] * 40, 11.0).replace(" 1.0 ", " \u0661\u0662 ", 1),
         ["range 1 of 40 is '\u0661\u0662'"]),
        (flaser([1.0, 2.0, 3.0, 4.0], 11.0).replace(" 11.0 ", " 1_1.0 ", 1),
         ["ipc_timestamp is '1_1.0'"]),
        ("ODOM 0 0 0 0 0 0", ["ODOM has 6 values, not 9"]),
        ("ODOM 0 0 zero 0 0 0 1.0 h 1.0", ["theta is 'zero'"]),
        ("PARAM lonely", ["PARAM needs a name and a value"]),
        ("12.5 3.0 4.0", ["not a CARMEN message: '12.5' is not a message name"]),
    ],
)
def test_malformed_line(tmp_path, bad, words):
    path, line = _with_line(tmp_path, bad, position=5)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, line, *words)


def test_malformed_new_format(tmp_path):
    good = robotlaser([1.0, 2.0], [3.0, 4.0], 1.0, (0, 0, 0), (0, 0, 0))
    tokens = good.split()
    short = " ".join(tokens[:-4] + tokens[-3:])  # turn_axis missing
    path = write(tmp_path, [good, short])
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 2, "declares 2 ranges and 2 remissions", "should have 28 tokens",
            "but it has 27")  # fmt: skip
    bad_count = " ".join(tokens[:11] + ["two"] + tokens[12:])  # the remission count
    path = write(tmp_path, [good, bad_count])
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 2, "num_remissions (the token after 2 ranges) is 'two'")


def test_skip_bad_lines(tmp_path):
    lines = old_log()
    lines.insert(3, "FLASER 4 1 2 3")
    lines.insert(5, "ODOM 1 2 x 0 0 0 1.0 h 1.0")
    lines.insert(6, "garbage, not a message")
    path = write(tmp_path, lines)
    log = read_carmen(path, skip_bad_lines=True)
    assert log.bad_lines == 3
    assert len(log.scans) == 3 and len(log.odometry) == 2
    np.testing.assert_array_equal(log.scans.timestamps, [10.05, 10.15, 10.15])


def test_different_beam_counts(tmp_path):
    # Old format: each scan's angles follow CARMEN's convention for its own count.
    path, _ = _with_line(tmp_path, flaser([1.0, 2.0, 3.0], 10.15), position=12)
    scans = read_carmen(path).scans
    assert scans.per_scan_geometry and scans.n_beams == 4
    np.testing.assert_array_equal(scans.beam_counts, [4, 4, 3, 4])
    np.testing.assert_allclose(scans.scan_angles(2), np.array([-90, 0, 90]) * DEG, atol=1e-12)
    np.testing.assert_allclose(scans.scan_angles(0), np.array([-90, -45, 0, 45]) * DEG, atol=1e-12)
    np.testing.assert_array_equal(scans.scan_ranges(2), [1.0, 2.0, 3.0])


def interlaced_lines(n=8, max_range=81.9):
    """ROBOTLASER1 lines as the Freiburg hospital's interlaced SICK logs them: 181 beams from -90°,
    then 180 beams from -89.75°, -89.5°, -89.25°, in turn, all at 1°."""
    lines = []
    for i in range(n):
        offset = [0.0, 0.75, 0.25, 0.5][i % 4]
        count = 181 if offset == 0.0 else 180
        ranges = [round(1.0 + 0.01 * b + i, 3) for b in range(count)]
        ranges[5] = 81.91  # no echo
        lines.append(robotlaser(ranges, [], 10.0 + 0.1 * i, (0.1 * i, 0, 0), (0.1 * i, 0, 0),
                                start=(-90 + offset) * DEG, max_range=max_range))  # fmt: skip
    return lines


def test_geometry_change_in_new_format(tmp_path):
    path = write(tmp_path, interlaced_lines())
    scans = read_carmen(path).scans
    assert scans.per_scan_geometry and scans.n_beams == 181 and len(scans) == 8
    np.testing.assert_array_equal(scans.beam_counts, [181, 180, 180, 180] * 2)
    first = [np.degrees(scans.scan_angles(i)[0]) for i in range(4)]
    np.testing.assert_allclose(first, [-90.0, -89.25, -89.75, -89.5], atol=1e-9)
    np.testing.assert_allclose(np.degrees(scans.scan_angles(1)[-1]), 89.75, atol=1e-9)
    assert scans.ranges[1, 180] == np.inf and np.isnan(scans.angles[1, 180])  # padding
    assert np.isinf(scans.ranges[:, 5]).all()  # 81.91 >= the message's 81.9: no echo
    np.testing.assert_array_equal(scans.scan_ranges(3)[:3], np.float32([4.0, 4.01, 4.02]))
    assert scans.max_range == 81.9 and scans.max_range_rule == "ROBOTLASER1 maximum_range field"


def test_varying_geometry_round_trip(tmp_path):
    from omnitof.io.carmen import write_carmen

    scans = read_carmen(write(tmp_path, interlaced_lines())).scans
    path = tmp_path / "again.clf.gz"
    write_carmen(path, scans)
    back = read_carmen(path).scans
    np.testing.assert_array_equal(back.beam_counts, scans.beam_counts)
    np.testing.assert_allclose(back.angles, scans.angles, atol=1e-12)  # NaN padding too
    np.testing.assert_array_equal(back.ranges, scans.ranges)
    np.testing.assert_allclose(back.odometry, scans.odometry, atol=1e-9)
    # A log whose scans share one geometry reads back with one (B,) angles.
    fixed = read_carmen(write(tmp_path, [interlaced_lines()[0], interlaced_lines(5)[4]])).scans
    assert not fixed.per_scan_geometry and fixed.n_beams == 181


def test_timestamps_going_backwards(tmp_path):
    lines = [flaser([1.0], t) for t in (10.0, 10.2, 10.1, 10.4, 8.0)]
    path = write(tmp_path, lines)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 5, "timestamps go backwards: 8.000000 follows 10.400000 (line 4)",
            "the clock was set back: split the log before line 5")
    # One stamp written hours ahead: the line to mend is named, not the one after it.
    (tmp_path / "spike").mkdir()
    with pytest.raises(InputError) as excinfo:
        read_carmen(write(tmp_path / "spike", [flaser([1.0], t) for t in (10.0, 10.1, 9999.0, 10.3, 10.4)]))
    assert "line 3's stamp lies ahead of the scans on both sides of it: correct or delete that line" in str(
        excinfo.value)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path, max_time_reversal=0.0)
    rejects(excinfo, path, 3, "10.100000 follows 10.200000")
    # A stamp of 1e300 was printed with all its 300 digits, twice; now it is no stamp at all.
    far = write(tmp_path, [flaser([1.0], t) for t in (10.0, 1e300, 10.4)])
    with pytest.raises(InputError) as excinfo:
        read_carmen(far)
    rejects(excinfo, far, 2, "ipc_timestamp 1e+300 is beyond ±1e+12 s: CARMEN timestamps are seconds")
    assert len(str(excinfo.value)) < 300
    path = write(tmp_path, lines[:4])
    with pytest.warns(CarmenWarning, match="1 FLASER timestamps are earlier.*first at line 3"):
        log = read_carmen(path)
    assert log.time_reversals == 1
    np.testing.assert_array_equal(log.scans.timestamps, [10.0, 10.2, 10.1, 10.4])


def test_a_repeated_line_is_dropped_and_a_shared_stamp_kept(tmp_path):
    # A line logged twice is one scan; a scan stamped like the one before it but reading
    # differently is a second reading (kept in file order); a small step back is kept too.
    # ScanSequence.time_order counts each kind.
    lines = [flaser([1.0, 2.0], 10.0), flaser([1.1, 2.0], 10.1), flaser([1.1, 2.0], 10.1),
             flaser([1.2, 2.0], 10.1), flaser([1.3, 2.0], 10.3), flaser([1.4, 2.0], 10.2)]
    path = write(tmp_path, lines)
    with pytest.warns(CarmenWarning) as record:
        log = read_carmen(path)
    messages = " | ".join(str(w.message) for w in record)
    assert "1 FLASER scans repeat the scan before them exactly" in messages
    assert "1 FLASER timestamps are earlier than the one before" in messages
    assert log.repeated_scans == 1 and log.time_reversals == 1
    np.testing.assert_array_equal(log.scans.timestamps, [10.0, 10.1, 10.1, 10.3, 10.2])
    np.testing.assert_allclose(log.scans.ranges[:, 0], [1.0, 1.1, 1.2, 1.3, 1.4])
    assert log.scans.time_order() == {"repeated_scans_dropped": 1, "equal_stamps": 1, "backward_steps": 1}


def _moving(t):
    """A robot driving at 0.5 m/s along x while turning at 0.6 rad/s (odometry linear in time,
    so interpolating it between messages is exact)."""
    return np.array([0.5 * t, 0.0, wrap_angle(0.6 * t - 0.3)])


def held_log(n_scans=40, odom_times=None, scan_phase=0.07, moving=_moving):
    """FLASER scans at 10 Hz that each carry the pose of the last ODOM message before them
    (sample-and-hold), ODOM at 10 Hz shifted by `scan_phase`; and the scans' true poses."""
    scan_times = 5.0 + 0.1 * np.arange(n_scans) + scan_phase
    odom_times = 5.0 + 0.1 * np.arange(n_scans + 1) if odom_times is None else odom_times
    events = sorted([(t, 0) for t in odom_times] + [(t, 1) for t in scan_times])  # ODOM first
    lines, last = [], None
    for t, kind in events:
        if kind == 0:
            last = moving(t)
            lines.append(odom(*last, t))
        elif last is not None:
            lines.append(flaser([1.0, 2.0], t, laser_pose=tuple(last)))
    return lines, np.array([moving(t) for t in scan_times if t >= odom_times[0]])


def test_held_odometry_is_interpolated_to_each_scan(tmp_path):
    # The ACES log's FLASER messages carry the last ODOM pose, a median 0.11 s old (95th
    # percentile 0.20 s): a constant scan delay cannot undo that, interpolating the ODOM
    # messages to the scan's stamp does.
    lines, truth = held_log()
    with pytest.warns(CarmenWarning, match=r"each FLASER message carries the last ODOM pose before it "
                                           r"\(median 0.070 s, 95th percentile 0.070 s old\)"):
        scans = read_carmen(write(tmp_path, lines)).scans
    np.testing.assert_allclose(scans.odometry, truth, atol=1e-9)
    assert scans.odometry_rule.startswith("interpolated from ODOM at each scan's timestamp")
    # The last scan lies after the last ODOM message: it keeps its logged pose.
    lines, truth = held_log(odom_times=5.0 + 0.1 * np.arange(40))
    with pytest.warns(CarmenWarning, match="last ODOM pose"):
        scans = read_carmen(write(tmp_path, lines)).scans
    np.testing.assert_allclose(scans.odometry[:-1], truth[:-1], atol=1e-9)
    np.testing.assert_allclose(scans.odometry[-1], _moving(5.0 + 0.1 * 39), atol=1e-9)
    assert scans.odometry_rule.endswith("; scans with no ODOM span around them, kept as logged: 1")


def test_held_odometry_is_found_where_each_odom_line_is_doubled(tmp_path):
    # Some loggers write each ODOM message twice; the copy must not read as a robot standing still.
    lines, truth = held_log()
    doubled = [copy for line in lines for copy in ([line, line] if line.startswith("ODOM") else [line])]
    with pytest.warns(CarmenWarning, match="last ODOM pose"):
        scans = read_carmen(write(tmp_path, doubled)).scans
    np.testing.assert_allclose(scans.odometry, truth, atol=1e-9)


def test_held_odometry_survives_a_jittered_stamp_and_an_odom_line_out_of_order(tmp_path):
    # A scan stamped 0.5 s early (its place in the file is right) is interpolated no further
    # than the ODOM message before the one before it; one ODOM line copied out of order (1 step
    # of 150 goes backwards) leaves the other scans interpolated.
    lines, truth = held_log(n_scans=150)
    scan_rows = [k for k, line in enumerate(lines) if line.startswith("FLASER")]
    k = scan_rows[60]
    fields = lines[k].split()
    fields[-3] = f"{float(fields[-3]) - 0.5:.6f}"
    lines[k] = " ".join(fields)
    odom_rows = [k for k, line in enumerate(lines) if line.startswith("ODOM")]
    lines.insert(odom_rows[100] + 1, lines[odom_rows[20]])
    with pytest.warns(CarmenWarning, match="last ODOM pose"):
        scans = read_carmen(write(tmp_path, lines)).scans
    assert "clamped to theirs: 1" in scans.odometry_rule
    np.testing.assert_allclose(scans.odometry[60], _moving(5.0 + 0.1 * 59), atol=1e-9)  # ODOM before the one before
    others = np.arange(len(truth)) != 60
    np.testing.assert_allclose(scans.odometry[others], truth[others], atol=1e-9)


def test_a_short_held_log_with_one_stray_odom_line_and_every_line_doubled_is_interpolated(tmp_path):
    # 90 scans (one stray step in 91 is over 1 %: still a stray line, not an unsteady clock),
    # each ODOM line written twice (the slack then reaches the message beyond the copy), and one
    # scan stamped 0.05 s before the ODOM line written before it: every pose exact.
    lines, truth = held_log(n_scans=90)
    odom_rows = [k for k, line in enumerate(lines) if line.startswith("ODOM")]
    lines.insert(odom_rows[60] + 1, lines[odom_rows[20]])
    scan_rows = [k for k, line in enumerate(lines) if line.startswith("FLASER")]
    fields = lines[scan_rows[30]].split()
    fields[-3] = f"{float(fields[-3]) - 0.12:.6f}"  # 5.0 + 3.0 + 0.07 - 0.12: before its ODOM line
    lines[scan_rows[30]] = " ".join(fields)
    truth[30] = _moving(5.0 + 3.07 - 0.12)
    doubled = [copy for line in lines for copy in ([line, line] if line.startswith("ODOM") else [line])]
    with pytest.warns(CarmenWarning, match="last ODOM pose"):
        scans = read_carmen(write(tmp_path, doubled)).scans
    np.testing.assert_allclose(scans.odometry, truth, atol=1e-9)
    assert scans.odometry_rule.endswith("; ODOM lines stamped out of order, left out: 1")


def test_odometry_with_absurd_stamps_is_refused_not_read_as_nan(tmp_path):
    # ODOM stamps of -1e308 s and then 1e308 s, the scans just after: the span between the
    # first two overflowed to inf and its weight was NaN; such stamps are no seconds at all.
    big = 1e308
    lines = [odom(0.0, 0.0, 0.0, -big)]
    for k in range(40):
        lines.append(flaser([1.0, 2.0], float(np.nextafter(big, np.inf)), laser_pose=(0.1 * k, 0.0, 0.0)))
        lines.append(odom(0.1 * (k + 1), 0.0, 0.0, big))
    path = write(tmp_path, lines)
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 1, "ipc_timestamp -1e+308 is beyond ±1e+12 s")


def test_one_odom_interval_is_no_held_odometry(tmp_path):
    # Two ODOM messages 3.2 s apart with 30 scans between them that repeat the first: too few
    # intervals to tell held odometry from a robot that logged its pose once.
    lines = [odom(0.0, 0.0, 0.0, 10.0)]
    lines += [flaser([1.0, 2.0], 10.1 + 0.1 * k, laser_pose=(0.0, 0.0, 0.0)) for k in range(30)]
    lines += [odom(1.0, 0.0, 0.3, 13.2)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = read_carmen(write(tmp_path, lines)).scans
    assert scans.odometry_rule == "the FLASER messages' robot poses"


def test_poses_at_the_scans_time_are_kept(tmp_path):
    # Freiburg 079's FLASER poses are interpolated to the scan already; a pose that only repeats
    # the ODOM before it while the robot stands still, or an ODOM stamped with its scan (as
    # write_carmen writes), is not held odometry.
    lines, truth = held_log()
    current = [flaser([1.0, 2.0], t, laser_pose=tuple(pose))
               for t, pose in zip(5.07 + 0.1 * np.arange(len(truth)), truth)]
    odoms = [line for line in lines if line.startswith("ODOM")]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = read_carmen(write(tmp_path, sorted(odoms + current, key=lambda l: float(l.split()[-3])))).scans
        np.testing.assert_array_equal(scans.odometry, truth)
        assert scans.odometry_rule == "the FLASER messages' robot poses"
        still, _ = held_log(moving=lambda t: np.array([1.0, 2.0, 0.5]))
        assert read_carmen(write(tmp_path, still)).scans.odometry_rule == "the FLASER messages' robot poses"
        fresh, _ = held_log(scan_phase=0.0)
        assert read_carmen(write(tmp_path, fresh)).scans.odometry_rule == "the FLASER messages' robot poses"


def test_held_odometry_with_odom_stamps_going_backwards_stays_as_logged(tmp_path):
    # The Intel log's ODOM stamps step back beyond single lines out of place: time then cannot
    # place them, so nothing changes, and poses held a median 0.07 s (well beyond
    # HELD_STALE_WARNING) are warned of. Here two ODOM lines in a row are stamped 0.25 s early
    # (a single one would be left out as a stray line, and the rest interpolated).
    def stepping_back(lines):
        lines = list(lines)
        for i in [k for k, line in enumerate(lines) if line.startswith("ODOM")][20:22]:
            x, y, theta, t = (float(v) for v in np.array(lines[i].split())[[1, 2, 3, 7]])
            lines[i] = odom(x, y, theta, t - 0.25)
        return lines

    def logged(lines):
        return np.array([[float(v) for v in line.split()[7:10]] for line in lines if line.startswith("FLASER")])

    lines = stepping_back(held_log()[0])
    with pytest.warns(CarmenWarning, match=r"median 0.070 s.*cannot be interpolated .* used as logged"):
        scans = read_carmen(write(tmp_path, lines)).scans
    np.testing.assert_array_equal(scans.odometry, logged(lines))
    assert "ODOM timestamps go backwards, so they were not interpolated" in scans.odometry_rule
    # Held for 2 ms at the median (the Intel log's: 0.3 ms): too fresh to warn of.
    mixed = 5.0 + 0.1 * np.arange(41) + np.where(np.arange(41) % 4 == 0, 0.0, 0.068)
    lines = stepping_back(held_log(odom_times=mixed)[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scans = read_carmen(write(tmp_path, lines)).scans
    np.testing.assert_array_equal(scans.odometry, logged(lines))
    assert "median 0.002 s, 95th percentile 0.079 s" in scans.odometry_rule  # the stepped-back ODOM lines are older


def test_missing_file(tmp_path):
    path = tmp_path / "nope.clf"
    with pytest.raises(InputError, match="file not found") as excinfo:
        read_carmen(path)
    assert excinfo.value.path == path and "nope.clf" in str(excinfo.value)


@pytest.mark.parametrize(
    "content, message",
    [
        (b"x,y\n1.0,2.0\n", "not a CARMEN log: the line starts with 'x,y'"),
        (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "not a CARMEN log: binary content"),
        (b"# only a comment\n", "not a CARMEN log: no PARAM, ODOM"),
        (b"", "not a CARMEN log"),
        (b"README FIRST\n", "not a CARMEN log"),
    ],
)
def test_not_a_carmen_log(tmp_path, content, message):
    path = tmp_path / "thing.clf"
    path.write_bytes(content)
    with pytest.raises(InputError, match=message) as excinfo:
        read_carmen(path)
    assert "thing.clf" in str(excinfo.value)


def test_corrupt_compressed_file(tmp_path):
    path = tmp_path / "log.clf.gz"
    path.write_bytes(gzip.compress(("\n".join(old_log()) + "\n").encode())[:-30] + b"junk")
    with pytest.raises(InputError, match="cannot read the file"):
        read_carmen(path)


def test_no_scans_of_chosen_laser(tmp_path):
    path = write(tmp_path, [odom(0, 0, 0, 1.0), flaser([1.0], 1.0, name="RLASER")])
    with pytest.raises(InputError, match="no front laser scans") as excinfo:
        read_carmen(path)
    assert excinfo.value.path == path and excinfo.value.line is None


def test_bad_param_value(tmp_path):
    path = write(tmp_path, ["PARAM robot_front_laser_max far nohost 0", flaser([1.0], 1.0)])
    with pytest.raises(InputError) as excinfo:
        read_carmen(path)
    rejects(excinfo, path, 1, "robot_front_laser_max is 'far'")


def test_bad_options(tmp_path):
    path = write(tmp_path, old_log())
    with pytest.raises(ConfigError, match="laser must be"):
        read_carmen(path, laser="left")
    with pytest.raises(ConfigError, match="fov_deg"):
        read_carmen(path, fov_deg=0.0)


# --------------------------------------------------------------------------------------------
# The bundled real logs (PROVENANCE.md of the data folder)

DATA = os.environ.get("OMNITOF_DATA")
needs_data = pytest.mark.skipif(
    not DATA,
    reason="OMNITOF_DATA is not set (the folder holding intel.clf.bz2, fr079.clf.bz2 and their "
    ".relations files)",
)

REAL_LOGS = {
    # name: scans, beams, path length of the laser poses (PROVENANCE.md), time reversals
    "intel": (13631, 180, 508.4, 631),
    "fr079": (4934, 360, 392.9, 0),
}


@functools.lru_cache(maxsize=None)
def _load_real(name: str):
    with warnings.catch_warnings():
        # intel's stamps step back (checked below); nothing else may warn.
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", ".*timestamps are earlier", CarmenWarning)
        return read_carmen(Path(DATA) / f"{name}.clf.bz2")


@pytest.fixture(params=sorted(REAL_LOGS))
def real_log(request):
    return request.param, _load_real(request.param)


@needs_data
def test_real_log_shape(real_log):
    name, log = real_log
    n_scans, n_beams, _, reversals = REAL_LOGS[name]
    assert len(log.scans) == n_scans and log.scans.n_beams == n_beams
    assert log.bad_lines == 0 and log.ignored_messages == {}
    # Intel's ipc stamps jitter back by up to 0.9 s while its poses run smoothly in file order.
    assert log.time_reversals == reversals
    no_echo = np.mean(~np.isfinite(log.scans.ranges))
    assert 0.005 < no_echo < 0.1  # 2.8 % (intel), 2.1 % (fr079)
    assert np.all(log.scans.ranges[np.isfinite(log.scans.ranges)] > 0)


@needs_data
def test_real_log_path_length(real_log):
    # PROVENANCE's figure is the path of the FLASER *laser* poses: for fr079 (laser 4 cm behind
    # the robot centre) the robot's odometry path is 391.6 m and the ODOM messages' 391.8 m.
    name, log = real_log
    laser_poses = compose(log.scans.odometry, log.scans.sensor_pose)
    length = np.sum(np.hypot(*np.diff(laser_poses[:, :2], axis=0).T))
    assert abs(length - REAL_LOGS[name][2]) < 1.0


@needs_data
def test_real_log_relations_match_scans(real_log):
    name, log = real_log
    relations = np.loadtxt(Path(DATA) / f"{name}.relations", ndmin=2)
    stamps = np.sort(log.scans.timestamps)
    wanted = relations[:, :2].ravel()
    i = np.clip(np.searchsorted(stamps, wanted), 1, len(stamps) - 1)
    nearest = np.minimum(np.abs(stamps[i] - wanted), np.abs(stamps[i - 1] - wanted))
    assert nearest.max() < 1e-4


@needs_data
def test_real_fr079_sensor_pose():
    log = _load_real("fr079")
    # PARAM robot_frontlaser_offset -0.04 and the FLASER poses agree: 4 cm behind the centre.
    np.testing.assert_allclose(log.scans.sensor_pose, [-0.04, 0.0, 0.0], atol=1e-4)
    assert log.scans.max_range == 80.99  # PARAM robot_front_laser_max


@pytest.mark.parametrize("suffix", [".log", ".log.gz", ".log.bz2"])
def test_write_carmen_round_trip(tmp_path, suffix):
    from omnitof.io.carmen import write_carmen
    from omnitof.sim.laser2d import make_loop_dataset

    scans = make_loop_dataset(seed=2, sensor_pose=(0.2, -0.05, 0.1)).slice(0, 60)
    path = tmp_path / f"out{suffix}"
    write_carmen(path, scans)
    back = read_carmen(path).scans
    assert len(back) == len(scans)
    assert np.allclose(back.angles, scans.angles, atol=1e-8)
    assert np.array_equal(np.isinf(back.ranges), np.isinf(scans.ranges))
    finite = np.isfinite(scans.ranges)
    assert np.allclose(back.ranges[finite], scans.ranges[finite], atol=5e-4 + 1e-6)
    assert np.allclose(back.odometry, scans.odometry, atol=1e-6)
    assert np.allclose(back.sensor_pose, scans.sensor_pose, atol=1e-5)
    assert np.allclose(back.timestamps, scans.timestamps, atol=1e-6)
    assert back.max_range == scans.max_range


def _two_scans(**fields) -> ScanSequence:
    given = {"timestamps": [1.0, 2.0], "ranges": np.ones((2, 3)), "angles": [-0.1, 0.0, 0.1],
             "odometry": np.zeros((2, 3)), "max_range": 8.0}
    return ScanSequence(**{**given, **fields})


@pytest.mark.parametrize(
    ("fields", "hostname", "message"),
    [
        ({}, "my host", "hostname must be one word, without whitespace or NUL, got 'my host'"),
        ({}, "", "hostname must be one word, without whitespace or NUL, got ''"),
        ({}, "a\x1cb", r"hostname must be one word, without whitespace or NUL, got 'a\\x1cb'"),
        ({}, "a\0b", r"hostname must be one word, without whitespace or NUL, got 'a\\x00b'"),
        ({"odometry": [[0, 0, 0], [np.nan, 0, 0]]}, HOST, r"scan 1 is not finite: timestamp 2.0, odometry \[nan, 0.0, 0.0\]"),
        ({"timestamps": [1.0, np.inf]}, HOST, "scan 1 is not finite: timestamp inf"),
        ({"timestamps": [np.nan, 1.0]}, HOST, "scan 0 is not finite: timestamp nan"),
        ({"max_range": np.inf}, HOST, "max_range must be a finite number of at least 1 mm and at most 1e.06 m, got inf"),
        ({"max_range": 0.0004}, HOST, "max_range must be a finite number of at least 1 mm and at most 1e.06 m, got 0.0004"),
        ({"max_range": 1e300}, HOST, "max_range must be a finite number of at least 1 mm and at most 1e.06 m, got 1e.300"),
        ({"sensor_pose": [0.0, np.nan, 0.0]}, HOST, r"sensor_pose is not finite: \[0.0, nan, 0.0\]"),
        ({"timestamps": [1.0, 1.7e12]}, HOST, r"scan 1: its timestamp is beyond ±1e\+12 s, which read_carmen refuses"),
        ({"odometry": [[0, 0, 0], [0, -2e9, 0]]}, HOST, r"scan 1: its position is beyond ±1e\+09 m"),
        ({"odometry": [[0, 0, 2e6], [0, 0, 0]]}, HOST, r"scan 0: its heading is beyond ±1e\+06 rad"),
        ({"timestamps": [5.0, 1.0]}, HOST,
         "scan 1: its timestamp 1.000000 is 4.000000 s before the one of scan 0; read_carmen tolerates at most 1.0 s"),
        ({"timestamps": [], "ranges": np.ones((0, 3)), "odometry": np.zeros((0, 3))}, HOST,
         "no scans to write: a CARMEN log needs at least one"),
        ({"ranges": np.ones((2, 0)), "angles": np.zeros(0)}, HOST, "the scans have no beam; ROBOTLASER1 needs one"),
        ({"angles": [[-0.1, 0.0, 0.1], [0.0, np.nan, np.nan]], "beam_counts": [3, 0]}, HOST,
         "scan 1 has no beam; ROBOTLASER1 needs one"),
    ],
)
def test_write_carmen_refuses_what_read_carmen_would(tmp_path, fields, hostname, message):
    from omnitof.io.carmen import write_carmen

    # Non-finite stamps and poses are set after the scans were made: ScanSequence refuses them.
    finite = {key: value for key, value in fields.items()
              if key not in ("odometry", "timestamps", "sensor_pose") or np.isfinite(value).all()}
    scans = _two_scans(**finite)
    for key in fields.keys() - finite.keys():
        setattr(scans, key, np.asarray(fields[key], dtype=np.float64))
    with pytest.raises(ValueError, match=message):
        write_carmen(tmp_path / "x.log", scans, hostname=hostname)
    assert list(tmp_path.iterdir()) == []


def test_write_carmen_keeps_small_clock_steps_back(tmp_path):
    # Real logs' clocks step back now and then; read_carmen tolerates up to 1 s (with a warning).
    from omnitof.io.carmen import write_carmen

    write_carmen(tmp_path / "x.log", _two_scans(timestamps=[2.0, 1.5]), hostname="robot-1")
    with pytest.warns(CarmenWarning, match="earlier than the one before"):
        back = read_carmen(tmp_path / "x.log").scans
    np.testing.assert_array_equal(back.timestamps, [2.0, 1.5])
    np.testing.assert_array_equal(back.ranges, np.ones((2, 3)))
