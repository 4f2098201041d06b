"""Tests of omnitof.io.tum and of the atomic writer it relies on."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from omnitof.errors import InputError
from omnitof.io.atomic import atomic_write
from omnitof.io.tum import ROW_MESSAGE, read_tum, write_tum
from omnitof.types import Trajectory


def _trajectory() -> Trajectory:
    # Unix-like times with microsecond parts, yaws all around the circle including near +-pi.
    t = 976052896.784509 + np.array([0.0, 0.123456, 1.5, 2.000001, 7.25])
    poses = np.array(
        [
            [0.0, 0.0, 0.0],
            [1.5, -2.25, 0.3],
            [-3.0, 4.0, -2.9],
            [10.0, 0.001, 3.14],
            [0.5, 0.5, -1.0],
        ]
    )
    return Trajectory(t, poses)


def test_round_trip(tmp_path: Path) -> None:
    traj = _trajectory()
    path = tmp_path / "traj.tum"
    write_tum(path, traj)
    back = read_tum(path)
    np.testing.assert_allclose(back.timestamps, traj.timestamps, rtol=0, atol=1e-6)
    np.testing.assert_allclose(back.poses[:, :2], traj.poses[:, :2], atol=1e-6)
    yaw_diff = np.angle(np.exp(1j * (back.poses[:, 2] - traj.poses[:, 2])))
    np.testing.assert_allclose(yaw_diff, 0.0, atol=1e-8)


def test_written_rows(tmp_path: Path) -> None:
    path = tmp_path / "traj.tum"
    write_tum(path, Trajectory([1234567890.000001], [[1.0, 2.0, np.pi / 2]]))
    lines = path.read_text().splitlines()
    assert lines[0].startswith("#") and lines[0].split()[1:] == [
        "timestamp",
        "x",
        "y",
        "z",
        "qx",
        "qy",
        "qz",
        "qw",
    ]
    fields = lines[1].split()
    assert fields[0] == "1234567890.000001"  # microseconds survive
    values = np.array(fields, dtype=float)
    h = np.sqrt(0.5)
    np.testing.assert_allclose(values[1:], [1.0, 2.0, 0.0, 0.0, 0.0, h, h], atol=1e-9)


def test_reads_comments_blank_lines_and_unnormalised_quaternions(tmp_path: Path) -> None:
    path = tmp_path / "t.txt"
    # Second row: a quaternion for yaw 90 deg, scaled by 2 (yaw must not depend on the scale).
    path.write_text("# comment\n\n1.0 1 2 0.5 0 0 0 1\n  \n2.0 3 4 0 0 0 1.414214 1.414214\n")
    traj = read_tum(path)
    np.testing.assert_allclose(traj.timestamps, [1.0, 2.0])
    np.testing.assert_allclose(traj.poses, [[1, 2, 0], [3, 4, np.pi / 2]], atol=1e-6)


@pytest.mark.parametrize("row", ["1.0 2 3 4 0 0 0", "1.0 2 3 4 0 0 0 1 9"])
def test_bad_row_names_file_line_and_format(tmp_path: Path, row: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(f"# header\n0.5 0 0 0 0 0 0 1\n{row}\n")
    with pytest.raises(InputError) as info:
        read_tum(path)
    assert info.value.path == path and info.value.line == 3
    assert ROW_MESSAGE in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize(
    ("row", "message"),
    [
        ("1.0 2 3 a 0 0 0 1", "z is 'a', not a finite decimal number"),
        ("1.0 2 1_0 4 0 0 0 1", "y is '1_0', not a finite decimal number"),  # float() reads 10
        ("nan 2 3 4 0 0 0 1", "timestamp is 'nan', not a finite decimal number"),
        ("1.0 2 0x10 4 0 0 0 1", "y is '0x10', not a finite decimal number"),
        ("1.0 2 \u0661\u0662 4 0 0 0 1", "y is '\u0661\u0662', not a finite decimal number"),  # float() reads 12
        ("1.0 1e200 3 4 0 0 0 1", "x is 1e+200, beyond ±1e+09: not a plausible value"),
        ("1.0 2 3 4 0 0 1e300 1", "qz is 1e+300, beyond ±1000: not a plausible value"),
        ("1e300 2 3 4 0 0 0 1", "timestamp 1e+300 is beyond ±1e+12 s: TUM timestamps are seconds"),
        ("1.7e12 2 3 4 0 0 0 1", "timestamp 1.7e+12 is beyond ±1e+12 s"),  # Unix milliseconds
        ("1.7e18 2 3 4 0 0 0 1", "divided by 1e3 or 1e9"),  # Unix nanoseconds
        ("inf 2 3 4 0 0 0 1", "timestamp is 'inf', not a finite decimal number"),
    ],
)
def test_a_bad_field_is_named_with_its_value(tmp_path: Path, row: str, message: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(f"0.5 0 0 0 0 0 0 1\n{row}\n")
    with pytest.raises(InputError) as info:
        read_tum(path)
    assert info.value.line == 2 and message in str(info.value)


def test_counted_and_unix_timestamps_are_read(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    path.write_text("0 0 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n2 2 0 0 0 0 0 1\n")
    assert read_tum(path).timestamps.tolist() == [0.0, 1.0, 2.0]
    path.write_text("1700000000.123456 0 0 0 0 0 0 1\n999999999999.5 1 0 0 0 0 0 1\n")
    assert read_tum(path).timestamps.tolist() == [1700000000.123456, 999999999999.5]


def test_a_relations_file_given_as_a_trajectory_is_refused(tmp_path: Path) -> None:
    # Both have 8 numbers a row; read as TUM, a relation's t2 was x (976 052 905 m) and its yaw
    # qw, and `omnitof eval relations` scored it without a word.
    path = tmp_path / "intel.relations"
    path.write_text("976052896.784509 976052905.167303 -0.153130 -0.051420 0 0 0 -2.405850\n")
    with pytest.raises(InputError, match=r"second column is a time \(976052905.167303, 8.383 s after the first\), "
                       "not x: this is a relations file") as info:
        read_tum(path)
    assert info.value.line == 1
    # A robot far out (UTM northing, 5 000 km) at a Unix time is a trajectory, as is one near the origin.
    path.write_text("1700000000.0 5000000.0 400000.0 0 0 0 0 1\n1700000000.1 5000000.1 400000.0 0 0 0 0 1\n")
    assert read_tum(path).poses[:, 0].tolist() == [5000000.0, 5000000.1]
    path.write_text("0.5 0.6 0 0 0 0 0 1\n")
    assert read_tum(path).poses[0, 0] == 0.6


def test_non_increasing_timestamps(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    path.write_text("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match="increase") as info:
        read_tum(path)
    assert info.value.line == 3


@pytest.mark.parametrize("text", ["", "# only a header\n\n"])
def test_empty_file(tmp_path: Path, text: str) -> None:
    path = tmp_path / "empty.tum"
    path.write_text(text)
    with pytest.raises(InputError, match="empty"):
        read_tum(path)


def test_missing_file_is_an_input_error(tmp_path: Path) -> None:
    with pytest.raises(InputError) as info:
        read_tum(tmp_path / "nope.tum")
    assert info.value.path == tmp_path / "nope.tum"


def test_writer_refuses_unreadable_trajectory(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="must not decrease"):
        write_tum(tmp_path / "t.tum", Trajectory([1.0, 0.5], np.zeros((2, 3))))
    assert list(tmp_path.iterdir()) == []


def test_poses_sharing_a_stamp_become_one_row_the_last(tmp_path: Path) -> None:
    # Equal stamps (and stamps equal to the microsecond the file keeps) give one row each, the
    # last pose in the trajectory's order; the file reads back, and the writer says how many
    # poses it left out.
    t = np.array([5.0, 5.0, 4.0, 6.0, 6.0000001, 7.0])
    poses = np.column_stack([np.arange(6.0), np.zeros(6), np.zeros(6)])
    path = tmp_path / "t.tum"
    assert write_tum(path, Trajectory(t, poses), sort=True) == 2
    back = read_tum(path)
    assert np.allclose(back.timestamps, [4.0, 5.0, 6.0, 7.0])
    assert back.poses[:, 0].tolist() == [2.0, 1.0, 4.0, 5.0]
    assert write_tum(path, Trajectory([1.0, 2.0], np.zeros((2, 3)))) == 0


def test_atomic_write_replaces_only_on_success(tmp_path: Path) -> None:
    path = tmp_path / "out.txt"
    with atomic_write(path) as f:
        f.write("first\n")
    assert path.read_text() == "first\n"
    with pytest.raises(RuntimeError), atomic_write(path) as f:
        f.write("half a")
        raise RuntimeError("interrupted")
    assert path.read_text() == "first\n"  # the old content survives
    assert [p.name for p in tmp_path.iterdir()] == ["out.txt"]  # no temp file left


def test_atomic_write_leaves_nothing_on_error(tmp_path: Path) -> None:
    path = tmp_path / "new.bin"
    with pytest.raises(KeyboardInterrupt), atomic_write(path, "wb") as f:
        f.write(b"\x00\x01")
        raise KeyboardInterrupt
    assert list(tmp_path.iterdir()) == []


def test_atomic_write_binary_and_mode_check(tmp_path: Path) -> None:
    with atomic_write(tmp_path / "b.bin", "wb") as f:
        f.write(b"\x00\xff")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\xff"
    with pytest.raises(ValueError), atomic_write(tmp_path / "c", "a"):
        pass


def test_write_sorted_keeps_each_pose_with_its_timestamp(tmp_path):
    # A log whose clock stepped back: rows come out in time order, each pose with its own stamp.
    t = np.array([10.0, 10.2, 10.1, 10.3])
    poses = np.array([[0.0, 0, 0], [2.0, 0, 0.2], [1.0, 0, 0.1], [3.0, 0, 0.3]])
    path = tmp_path / "t.tum"
    with pytest.raises(ValueError, match="must not decrease"):
        write_tum(path, Trajectory(t, poses))
    write_tum(path, Trajectory(t, poses), sort=True)
    back = read_tum(path)
    assert np.allclose(back.timestamps, [10.0, 10.1, 10.2, 10.3])
    assert np.allclose(back.poses[:, 0], [0.0, 1.0, 2.0, 3.0])
    assert np.allclose(back.poses[:, 2], [0.0, 0.1, 0.2, 0.3])


@pytest.mark.parametrize(
    ("t", "poses", "message"),
    [
        ([0.0, np.nan, 0.5], np.zeros((3, 3)), r"trajectory pose 1 is not finite: timestamp nan, pose \[0.0, 0.0, 0.0\]"),
        ([0.0, 1.0, np.inf], np.zeros((3, 3)), "trajectory pose 2 is not finite: timestamp inf"),
        ([0.0, 1.0], [[0.0, 0.0, 0.0], [np.nan, 0.0, 0.0]], r"trajectory pose 1 is not finite: timestamp 1.0, pose \[nan, 0.0, 0.0\]"),
        ([0.0, 1.0], [[0.0, 0.0, -np.inf], [0.0, 0.0, 0.0]], "trajectory pose 0 is not finite"),
        ([0.0, 1.0], [[0.0, 0.0, 0.0], [0.0, 2e9, 0.0]], r"trajectory pose 1 lies beyond ±1e\+09 m: \[0.0, 2000000000.0\]"),
        ([0.0, 1.7e12], np.zeros((2, 3)), r"trajectory pose 1 has timestamp 1.7e\+12, beyond ±1e\+12 s"),
    ],
)
@pytest.mark.parametrize("sort", [False, True])
def test_writer_refuses_poses_the_reader_would_refuse(
    tmp_path: Path, t: list[float], poses: np.ndarray, message: str, sort: bool
) -> None:
    with pytest.raises(ValueError, match=message):
        write_tum(tmp_path / "t.tum", Trajectory(t, np.asarray(poses, dtype=float)), sort=sort)
    assert list(tmp_path.iterdir()) == []


def test_writer_refuses_an_empty_trajectory(tmp_path: Path) -> None:
    # read_tum refuses a file without a pose, so none is written.
    with pytest.raises(ValueError, match="the trajectory has no pose; a TUM file needs at least one"):
        write_tum(tmp_path / "t.tum", Trajectory(np.zeros(0), np.zeros((0, 3))))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("separator", ["\x0c", "\x1c", "\x1d", "\x1e", "\x85", "\u2028", "\u2029", "\x0b"])
def test_line_numbers_count_newlines_only(tmp_path: Path, separator: str) -> None:
    # str.splitlines() breaks at these too; the line number of an error must not move.
    path = tmp_path / "t.tum"
    path.write_text(f"0 1 2 0 0 0 0 1{separator}\n1 1 2 0 0 0 0 1\nbad\n", encoding="utf-8")
    with pytest.raises(InputError) as info:
        read_tum(path)
    assert info.value.line == 3 and f"{path}:3: " in str(info.value)


def test_a_byte_order_mark_before_the_header_is_dropped(tmp_path: Path) -> None:
    # Windows editors write one; the header then read as a row of 9 fields.
    path = tmp_path / "t.tum"
    path.write_bytes("\ufeff# timestamp x y z qx qy qz qw\r\n0 1 2 0 0 0 0 1\r\n".encode())
    traj = read_tum(path)
    assert len(traj) == 1 and traj.poses[0, 0] == 1.0


def test_line_numbers_after_crlf_and_cr(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    path.write_bytes(b"0 1 2 0 0 0 0 1\r\n1 1 2 0 0 0 0 1\r2 1 2 0 0 0 0 1\nbad\n")
    with pytest.raises(InputError) as info:
        read_tum(path)
    assert info.value.line == 4
