"""Trajectories in the TUM RGB-D benchmark format.

One pose per line: `timestamp x y z qx qy qz qw` (seconds, metres, a unit quaternion giving the
orientation of the robot frame in the world frame, scalar last). omnitof is planar: it writes
z = 0 and a rotation about +z only, and on reading keeps x, y and the yaw of the quaternion
(z, roll and pitch are dropped). Lines starting with '#' are comments.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from omnitof.errors import InputError, read_problem
from omnitof.io.text import is_decimal, parse_float_row
from omnitof.geometry import check_headings, quaternion_to_yaw, yaw_to_quaternion
from omnitof.io.atomic import atomic_write
from omnitof.types import MAX_TIMESTAMP, Trajectory, first_non_finite

HEADER = "# timestamp x y z qx qy qz qw"
ROW_MESSAGE = "TUM trajectory rows need 8 numbers: timestamp x y z qx qy qz qw"
_FIELDS = ("timestamp", "x", "y", "z", "qx", "qy", "qz", "qw")
# Positions beyond a million kilometres (io.carmen's MAX_POSITION) and quaternions far from unit
# length come from a broken writer; the statistics over them overflow or print as hundreds of
# digits.
_LIMITS = {"x": 1e9, "y": 1e9, "z": 1e9, "qx": 1e3, "qy": 1e3, "qz": 1e3, "qw": 1e3}

# Unix times (~1e9 s) at microsecond precision need 6 decimals; positions to the micrometre, and
# quaternions to 1e-9 so that yaw survives a round trip to ~1e-9 rad.
_FORMATS = ["%.6f", "%.6f", "%.6f", "%.6f", "%.9f", "%.9f", "%.9f", "%.9f"]


def write_tum(path: str | Path, traj: Trajectory, *, sort: bool = False) -> int:
    """Write `traj` as a TUM trajectory file (atomically), with a '#' header naming the columns.

    With `sort`, rows are written in timestamp order. Some logs stamp their messages with clocks
    that step back now and then (the Intel log's scans do, 631 times); each pose keeps its own
    timestamp, so ordering the rows loses nothing and keeps the file readable by TUM tools.

    A TUM file identifies a pose by its timestamp, so it holds one row per timestamp as written
    (to the microsecond): where several poses share one (a log whose stamps repeat, see
    `omnitof.types.drop_repeated_scans`), the last of them in the trajectory's order is
    written, the latest estimate. Returns how many poses were left out so.

    Raises:
        ValueError: for what `read_tum` would refuse to read back: no pose, a timestamp or pose
            that is not finite (naming the pose), a position beyond ±1e9 m, or, without `sort`,
            timestamps that decrease.
    """
    _check_poses(traj)
    if sort:
        order = np.argsort(traj.timestamps, kind="stable")
        traj = Trajectory(traj.timestamps[order], traj.poses[order])
    _check_increasing(traj.timestamps)
    stamps = np.char.mod(_FORMATS[0], traj.timestamps)
    last = np.append(stamps[1:] != stamps[:-1], True)  # the last row of each written stamp
    n = int(last.sum())
    data = np.empty((n, 8))
    data[:, 0] = traj.timestamps[last]
    data[:, 1:3] = traj.poses[last, :2]
    data[:, 3] = 0.0
    data[:, 4:8] = yaw_to_quaternion(traj.poses[last, 2])
    with atomic_write(path, "w") as f:
        f.write(HEADER + "\n")
        np.savetxt(f, data, fmt=_FORMATS, delimiter=" ")
    return len(traj) - n


def _check_poses(traj: Trajectory) -> None:
    if len(traj) == 0:
        raise ValueError("the trajectory has no pose; a TUM file needs at least one")
    i = first_non_finite(traj.timestamps, traj.poses)
    if i is not None:
        raise ValueError(
            f"trajectory pose {i} is not finite: timestamp {traj.timestamps[i]}, "
            f"pose {traj.poses[i].tolist()}"
        )
    check_headings(traj.poses, "trajectory")
    late = np.flatnonzero(np.abs(traj.timestamps) > MAX_TIMESTAMP)
    if late.size:
        i = int(late[0])
        raise ValueError(f"trajectory pose {i} has timestamp {traj.timestamps[i]:g}, beyond ±{MAX_TIMESTAMP:g} s")
    far = np.flatnonzero(np.abs(traj.poses[:, :2]).max(axis=1) > _LIMITS["x"])
    if far.size:
        i = int(far[0])
        raise ValueError(
            f"trajectory pose {i} lies beyond ±{_LIMITS['x']:g} m: {traj.poses[i, :2].tolist()}"
        )


def _check_increasing(timestamps: np.ndarray) -> None:
    bad = np.flatnonzero(np.diff(timestamps) < 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise ValueError(
            f"trajectory timestamps must not decrease: pose {i} at {timestamps[i]:.6f} "
            f"follows {timestamps[i - 1]:.6f}"
        )


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file; yaw comes from the quaternion.

    Raises:
        InputError: naming the file and line for a row that is not 8 finite numbers, a
            timestamp beyond ±1e12 s or position beyond ±1e9 m, a zero quaternion, or a
            timestamp that does not increase; naming the file if it cannot be read or holds no
            pose.
    """
    rows: list[list[float]] = []
    previous: tuple[float, int] | None = None  # (timestamp, line number) of the last row
    for number, line in enumerate(_read_lines(path), start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        row = _parse_row(text, path, number)
        if previous is not None and row[0] <= previous[0]:
            raise InputError(
                f"timestamps must increase: {row[0]:.6f} follows {previous[0]:.6f} "
                f"(line {previous[1]})",
                path,
                number,
            )
        previous = (row[0], number)
        rows.append(row)
    if not rows:
        raise InputError("no poses: the TUM trajectory file is empty", path)
    data = np.asarray(rows)
    return Trajectory(timestamps=data[:, 0], poses=np.column_stack([data[:, 1:3], _yaw(data)]))


def _read_lines(path: str | Path) -> list[str]:
    # Split on "\n" only (read_text folds "\r\n" and "\r" into it): splitlines() would also
    # break at form feeds, \x1c-\x1e, \x85 and \u2028, and every line number after them would be
    # wrong. utf-8-sig drops the byte order mark that Windows editors write first.
    try:
        return Path(path).read_text(encoding="utf-8-sig").split("\n")
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the TUM trajectory: {read_problem(exc)}", path) from None


def _parse_row(text: str, path: str | Path, number: int) -> list[float]:
    # Before the fields' limits: a relations row of today's Unix times has an "x" beyond 1e9 m,
    # which would be refused as a position instead of named for what it is.
    _refuse_relations(text, path, number)
    row = parse_float_row(text, 8, ROW_MESSAGE, path, number, names=_FIELDS, limits=_LIMITS)
    if abs(row[0]) > MAX_TIMESTAMP:
        raise InputError(f"timestamp {row[0]:g} is beyond ±{MAX_TIMESTAMP:g} s: TUM timestamps are seconds "
                         "(milliseconds or nanoseconds must be divided by 1e3 or 1e9)", path, number)
    if max(abs(v) for v in row[4:8]) < 1e-9:
        raise InputError("the quaternion qx qy qz qw has zero length", path, number)
    return row


def _refuse_relations(text: str, path: str | Path, number: int) -> None:
    """InputError where the row is a benchmark relation (`t1 t2 x y z roll pitch yaw`, 8 numbers
    as a TUM row has): its second column is then a time a little after the first, which read as
    x put the robot a billion metres out and gave a score of nonsense. No robot's x lies within
    a day after a timestamp of 10⁶ s or more (x ≥ 1000 km)."""
    fields = text.split()
    if len(fields) != 8 or not (is_decimal(fields[0]) and is_decimal(fields[1])):
        return
    t, x = float(fields[0]), float(fields[1])
    if t >= 1e6 and 0.0 < x - t <= 86400.0:
        raise InputError(
            f"the second column is a time ({fields[1]}, {x - t:.3f} s after the first), not x: this is a relations "
            "file (t1 t2 x y z roll pitch yaw); a TUM trajectory holds timestamp x y z qx qy qz qw",
            path, number)


def _yaw(data: np.ndarray) -> np.ndarray:
    # quaternion_to_yaw takes quaternions of any length (files rounded to a few decimals).
    return np.asarray(quaternion_to_yaw(data[:, 4:8]))
