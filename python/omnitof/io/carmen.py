"""Reading CARMEN laser logs (plain, gzip or bzip2) into a ScanSequence.

A CARMEN log holds one message per line; lines starting with '#' are comments. Every message ends
with `ipc_timestamp ipc_hostname logger_timestamp`, and the *ipc* timestamp is the one kept here:
the relation files of the Kümmerle et al. SLAM benchmark refer to scans by it.

Messages read (anything else is counted in `CarmenLog.ignored_messages`):

    PARAM name value [ipc_timestamp ipc_hostname logger_timestamp | ipc_hostname timestamp]
    ODOM x y theta tv rv accel <trailer>
    FLASER / RLASER n r_1..r_n laser_x laser_y laser_theta odom_x odom_y odom_theta <trailer>
    ROBOTLASER1 / ROBOTLASER2 laser_type start_angle fov angular_resolution maximum_range
        accuracy remission_mode n r_1..r_n m rem_1..rem_m laser_x laser_y laser_theta
        robot_x robot_y robot_theta tv rv forward_safety_dist side_safety_dist turn_axis <trailer>
    RAWLASER1..4  laser_type start_angle fov angular_resolution maximum_range accuracy
        remission_mode n r_1..r_n m rem_1..rem_m <trailer>

The front laser is FLASER / ROBOTLASER1 / RAWLASER1, the rear one RLASER / ROBOTLASER2 /
RAWLASER2. Messages that carry poses (FLASER, ROBOTLASER) are preferred; RAWLASER scans, which
carry none, are used only when there are no others, with the robot pose interpolated from ODOM.

Units and frames follow omnitof.types: metres, radians, seconds; poses (x, y, theta) with theta
counter-clockwise from +x; a range of +inf means "no echo".
"""

from __future__ import annotations

import bz2
import gzip
import io
import math
import re
import warnings
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO, Iterator

import numpy as np

from omnitof.errors import ConfigError, InputError, OmnitofWarning, read_problem
from omnitof.io.text import is_decimal, quote
from omnitof.geometry import MAX_HEADING, interpolate_poses, relative, wrap_angle
from omnitof.types import (
    MAX_BEAM_ANGLE,
    MAX_TIME_REVERSAL,
    MAX_TIMESTAMP,
    MIN_BEAM_STEP,
    ScanSequence,
    Trajectory,
    drop_repeated_scans,
    evenly_spaced_beams,
    first_non_finite,
    pad_rows,
)

__all__ = ["CarmenLog", "CarmenWarning", "old_format_angles", "read_carmen", "write_carmen"]

TRAILER = "ipc_timestamp ipc_hostname logger_timestamp"

# CARMEN's own reader assumes 80 m for old-format lasers; it also sits below the SICK no-return
# codes in the bundled logs (81.83 in intel, 81.91 in fr079).
DEFAULT_MAX_RANGE = 80.0

# The no-echo code of a laser whose log does not state its range (see repeated_top_value):
# the top reading below DEFAULT_MAX_RANGE counts as that code when it holds this share of all
# readings, at least this many of them, and this many times the count of any other value
# within TOP_VALUE_BAND (relative) below it.
TOP_VALUE_SHARE = 0.005
TOP_VALUE_MIN_COUNT = 100
TOP_VALUE_DOMINANCE = 10
TOP_VALUE_BAND = 0.05

# A laser bolted to the robot keeps its offset; CARMEN prints poses to 1e-6, so these tolerances
# only catch laser poses that are no mount at all (a corrected log's, next to raw odometry).
OFFSET_TOLERANCE_M = 0.01
OFFSET_TOLERANCE_RAD = math.radians(0.5)
# Laser poses count as a mount when this share of the scans agree with their median offset.
MOUNT_MIN_SHARE = 0.9

# Scans whose first and last beams agree with the first scan's to this (rad) share its geometry.
GEOMETRY_TOLERANCE = 1e-6
# The largest max_range write_carmen writes (m): no laser reaches 1000 km.
MAX_WRITTEN_RANGE = 1e6
# Poses beyond a million kilometres come from a broken logger, not a robot (georeferenced logs
# lie within 2e7 m); the trajectory files (io.tum) hold no more either.
MAX_POSITION = 1e9
# A laser mounted farther than this from the robot's centre is a mistaken offset (a PARAM in
# millimetres, a pose in another frame); the maps' cells could not hold its end points.
MAX_MOUNT = 100.0

# Held odometry (see _held_odometry): a laser message's pose counts as the last ODOM pose when it
# equals it to the logs' print precision, judged over at least this many scans taken while the
# odometry moved, this share of which must agree; and the ODOM message must be older than its
# scan by HELD_MIN_AGE in more than HELD_OLD_SHARE of them (not stamped with it).
HELD_POSE_TOLERANCE = 2e-6
HELD_MIN_SCANS = 20
HELD_MIN_INTERVALS = 10
HELD_MIN_SHARE = 0.95
HELD_MIN_AGE = 1e-3  # seconds
HELD_OLD_SHARE = 0.05
HELD_STALE_WARNING = 0.01  # seconds: held poses this old that cannot be interpolated are warned of

_KINDS = {  # laser side -> (old format, new format with poses, new format without poses)
    "front": ("FLASER", "ROBOTLASER1", "RAWLASER1"),
    "rear": ("RLASER", "ROBOTLASER2", "RAWLASER2"),
}
_ALL_LASER_KINDS = {"FLASER", "RLASER", "ROBOTLASER1", "ROBOTLASER2"} | {
    f"RAWLASER{i}" for i in range(1, 5)
}
# Message names known from CARMEN's logger; seeing one is what makes a file a CARMEN log.
_KNOWN_MESSAGES = _ALL_LASER_KINDS | {
    "PARAM", "ODOM", "SYNC", "TRUEPOS", "NMEA-GGA", "NMEAGGA", "NMEARMC", "GPSNMEA", "SONAR",
    "BUMPER", "IMU", "VELOCITY", "SCANMARK", "POSITIONLASER", "ROBOTLASER3", "ROBOTLASER4",
}  # fmt: skip
_MESSAGE_NAME = re.compile(r"[A-Z][A-Z0-9_-]*\Z")
_GZIP_MAGIC = b"\x1f\x8b"
_BZIP2_MAGIC = b"BZh"
_SNIFF_BYTES = 4096  # how much of the start is checked for binary content


class CarmenWarning(OmnitofWarning):
    """Something in a CARMEN log was accepted but deserves a look (see the message)."""


@dataclass
class CarmenLog:
    """The content of a CARMEN log that omnitof uses.

    Attributes:
        scans: the scans of the chosen laser, in file order, with their ipc timestamps.
        params: PARAM name -> value (the last one wins if a name repeats).
        odometry: every ODOM message, in file order: ipc timestamps and (x, y, theta).
        bad_lines: malformed lines skipped (only ever nonzero with skip_bad_lines=True).
        ignored_messages: message name -> count, for the messages not used (SYNC, TRUEPOS, the
            other laser, RAWLASER when the same laser also has messages with poses, ...).
        time_reversals: how many times a scan's timestamp is earlier than the one before it
            (tolerated up to `max_time_reversal`; see read_carmen).
        repeated_scans: scans dropped because they repeat the scan before them exactly (a
            line logged twice; see read_carmen).
    """

    scans: ScanSequence
    params: dict[str, str]
    odometry: Trajectory
    bad_lines: int = 0
    ignored_messages: dict[str, int] = field(default_factory=dict)
    time_reversals: int = 0
    repeated_scans: int = 0


def read_carmen(
    path: str | Path,
    *,
    skip_bad_lines: bool = False,
    laser: str = "front",
    fov_deg: float = 180.0,
    max_time_reversal: float = MAX_TIME_REVERSAL,
) -> CarmenLog:
    """Read a CARMEN log (plain text, gzip or bzip2, told apart by the file's magic bytes).

    Beam angles. New-format messages state them: beam i is at start_angle + i *
    angular_resolution. Old-format FLASER/RLASER messages state only the beam count n, so the
    angles follow CARMEN's own reader (readlog.c, `carmen_string_to_robot_laser_message_orig`):
    a SICK LMS sweeps the field of view with a beam at *both* ends (181 beams at 1°, 361 at
    0.5°), and a log with an even count (180, 360) dropped the last one. Hence

        start = -fov/2,  step = fov/n for even n, fov/(n - 1) for odd n,

    i.e. -90°..+89° at 1° for intel's 180 beams and -90°..+89.5° at 0.5° for fr079's 360 beams,
    not the symmetric -89.5°..+89.5° one might assume. The field of view is the PARAM
    `laser_front_laser_fov` (`laser_rear_laser_fov`; degrees) when the log has it, else
    `fov_deg`. (CARMEN itself always starts at -90° and, for beam counts it does not know, uses
    180°/(n - 1); GMapping's log reader places 180 beams at ±1°..±90° with no beam at 0°; MRPT
    spreads them evenly over -90°..+90°. The disagreement is at most one step.)
    The geometry may change from scan to scan (count, start angle, resolution: the Freiburg
    hospital's interlaced SICK alternates four start angles); the ScanSequence then carries it per
    scan (`angles` (N, B), `beam_counts`), else one `angles` (B,) for the whole log.

    Sensor pose (ScanSequence.sensor_pose, robot_T_sensor). From the per-message laser and robot
    poses of FLASER/ROBOTLASER when they differ: the laser pose in the robot's frame in the
    first scan, when it holds to 1 cm and 0.5° over the log (the median offset, with a
    CarmenWarning, when it holds for 90 % of the scans). Otherwise (laser poses that are no
    fixed mount, as in a corrected log: a CarmenWarning says so, and they are left out) from the
    PARAMs
    `robot_frontlaser_offset` (forward), `robot_frontlaser_side_offset` (left) and
    `robot_frontlaser_angular_offset` (`rearlaser` for the rear laser), taken literally as
    (x, y, theta); missing ones are 0, except that a rear laser with no angular offset faces
    backwards at (-offset, -side_offset, pi), as in older CARMEN (its localize module). If both
    exist and disagree, the messages win and a CarmenWarning says so.

    Odometry. ScanSequence.odometry is the robot pose of each scan: odom_x.. or robot_x.. as
    logged, or interpolated from ODOM at the scan's timestamp (linear in x and y, shortest arc
    in theta) for RAWLASER, and for a log whose laser messages hold the last ODOM pose instead
    of the pose at the scan (`_held_odometry`; a CarmenWarning says so). Where such a log's
    ODOM timestamps go backwards beyond single lines out of place (Intel's), the held poses are
    kept as logged, with a CarmenWarning if they are a median 10 ms old or more.
    `ScanSequence.odometry_rule` says which.

    No echo. A range >= the maximum range or <= 0 becomes +inf. The maximum is the message's
    maximum_range in the new format (each scan its own); for FLASER/RLASER it is the PARAM
    `robot_front_laser_max` (`robot_rear_laser_max`), else `laser_front_laser_max_range`, else
    80 m, lowered to a value that repeats at the top of the readings below 80 m (a laser's own
    no-echo code, such as 50.00 m; see `repeated_top_value`), with a CarmenWarning.
    `ScanSequence.max_range_rule` says which rule gave it.

    Time order. Scans are kept in file order with their logged timestamps (the benchmark
    relations refer to them). A scan that repeats the one before it exactly (stamp, readings
    and pose: the same line logged twice) is dropped, counted in `CarmenLog.repeated_scans`
    and reported in a CarmenWarning (`omnitof.types.drop_repeated_scans`). A scan stamped like
    the one before it but reading differently is kept. A timestamp earlier than the previous
    one by at most `max_time_reversal` seconds is accepted too, counted in
    `CarmenLog.time_reversals` and reported once in a CarmenWarning: the Intel log has 631 such
    steps of up to 0.9 s while its poses run smoothly in file order, so the file order is right
    and the stamps jitter. `ScanSequence.time_order` counts both kinds.

    Args:
        path: the log file.
        skip_bad_lines: count malformed lines in `bad_lines` and go on instead of raising.
        laser: "front" or "rear".
        fov_deg: field of view of old-format scans, degrees, when no PARAM gives it.
        max_time_reversal: the largest backwards step of scan timestamps tolerated, seconds
            (0 to refuse any).

    Raises:
        InputError: naming the file, and the line where there is one: a malformed line (unless
            skip_bad_lines), a missing or unreadable file, a file that is not a CARMEN log, no
            scans of the chosen laser, old- and new-format scans of the same laser, scan
            timestamps going backwards by more than max_time_reversal, RAWLASER scans outside
            the time span of the odometry.
        ConfigError: for a bad `laser`, `fov_deg` or `max_time_reversal`.
    """
    _check_options(laser, fov_deg, max_time_reversal)
    path = Path(path)
    ctx = _Context(path, skip_bad_lines)
    raw = _scan_file(ctx, laser)
    params = {name: value for name, (value, _) in raw.params.items()}
    odometry, odom_lines = _parse_odometry(ctx, raw.odom)
    kind = _choose_kind(ctx, raw, laser)
    records = _parse_scans(ctx, kind, raw.lasers[kind])
    scans = _build_sequence(ctx, kind, laser, records, raw.params, odometry, odom_lines, fov_deg)
    reversals = _check_time_order(ctx, kind, records, max_time_reversal)
    scans = drop_repeated_scans(scans)
    if scans.repeated_scans_dropped:
        warnings.warn(
            f"{ctx.path}: {scans.repeated_scans_dropped} {kind} scans repeat the scan before them "
            "exactly (stamp, readings and pose: a line logged twice) and were dropped",
            CarmenWarning,
            stacklevel=2,
        )
    return CarmenLog(
        scans=scans,
        params=params,
        odometry=odometry,
        bad_lines=ctx.bad_lines,
        ignored_messages=dict(sorted(raw.ignored.items())),
        time_reversals=reversals,
        repeated_scans=scans.repeated_scans_dropped,
    )


# --------------------------------------------------------------------------------------------
# File reading


class _Malformed(Exception):
    """A line that does not follow its message's layout; the text says what was expected."""


class _Context:
    """The file being read and what to do with malformed lines."""

    def __init__(self, path: Path, skip_bad_lines: bool):
        self.path = path
        self.skip_bad_lines = skip_bad_lines
        self.bad_lines = 0

    def reject(self, message: str, line: int) -> None:
        """Skip a malformed line (counting it) or raise, as the caller asked."""
        if not self.skip_bad_lines:
            raise InputError(message, self.path, line)
        self.bad_lines += 1

    def error(self, message: str, line: int | None = None) -> InputError:
        return InputError(message, self.path, line)


@dataclass
class _RawLog:
    """First pass over the file: lines grouped by use, not yet parsed (except PARAM)."""

    params: dict[str, tuple[str, int]] = field(default_factory=dict)  # name -> (value, line)
    odom: list[tuple[int, str]] = field(default_factory=list)
    lasers: dict[str, list[tuple[int, str]]] = field(default_factory=dict)
    ignored: Counter = field(default_factory=Counter)
    known_messages: int = 0


def _check_options(laser: str, fov_deg: float, max_time_reversal: float) -> None:
    if laser not in _KINDS:
        raise ConfigError(f"laser must be 'front' or 'rear', got {laser!r}")
    if not (0.0 < fov_deg <= 360.0):
        raise ConfigError(f"fov_deg must be in (0, 360], got {fov_deg!r}")
    if not (max_time_reversal >= 0.0):
        raise ConfigError(f"max_time_reversal must be >= 0 seconds, got {max_time_reversal!r}")


def _open_binary(path: Path) -> BinaryIO:
    """Open for reading bytes, decompressing by magic bytes (a .gz that is not gzip is plain)."""
    with path.open("rb") as f:
        magic = f.read(3)
    if magic.startswith(_GZIP_MAGIC):
        return gzip.open(path, "rb")
    if magic.startswith(_BZIP2_MAGIC):
        return bz2.open(path, "rb")
    return path.open("rb")


def _lines(ctx: _Context) -> Iterator[tuple[int, str]]:
    """(line number, text) of the non-blank, non-comment lines; file errors as InputError."""
    if not ctx.path.exists():
        raise ctx.error("file not found")
    if not ctx.path.is_file():
        raise ctx.error("not a file")
    try:
        with _open_binary(ctx.path) as raw:
            if b"\x00" in raw.peek(_SNIFF_BYTES)[:_SNIFF_BYTES]:
                raise ctx.error("not a CARMEN log: binary content (NUL bytes)")
            # Hostnames may hold any bytes; the numbers are ASCII, so never fail on decoding.
            # newline=None folds CRLF (and lone CR) line ends into "\n"; utf-8-sig drops the byte
            # order mark that some Windows editors write at the start.
            stream = io.TextIOWrapper(raw, encoding="utf-8-sig", errors="replace", newline=None)
            for number, line in enumerate(stream, start=1):
                text = line.strip()
                if text and not text.startswith("#"):
                    yield number, text
    except (OSError, EOFError, zlib.error) as exc:
        raise ctx.error(f"cannot read the file: {read_problem(exc)}") from None


def _scan_file(ctx: _Context, laser: str) -> _RawLog:
    """Group the lines by message; parse PARAMs; count the messages that are not used."""
    raw = _RawLog()
    wanted = set(_KINDS[laser])
    for number, text in _lines(ctx):
        name = text.split(None, 1)[0]
        if name in _KNOWN_MESSAGES:
            raw.known_messages += 1
        if name == "PARAM":
            _add_param(ctx, raw, number, text.split())
        elif name == "ODOM":
            raw.odom.append((number, text))
        elif name in wanted:
            raw.lasers.setdefault(name, []).append((number, text))
        elif _MESSAGE_NAME.match(name):
            raw.ignored[name] += 1
        elif raw.known_messages == 0 and not ctx.skip_bad_lines:
            raise ctx.error(
                f"not a CARMEN log: the line starts with {quote(name)}; expected '#' comments "
                "and messages such as PARAM, ODOM, FLASER, ROBOTLASER1",
                number,
            )
        else:
            ctx.reject(f"not a CARMEN message: {quote(name)} is not a message name", number)
    if raw.known_messages == 0:
        raise ctx.error(
            "not a CARMEN log: no PARAM, ODOM, FLASER, ROBOTLASER or RAWLASER message in it"
        )
    return raw


def _add_param(ctx: _Context, raw: _RawLog, number: int, tokens: list[str]) -> None:
    """PARAM name value, optionally followed by `ipc_timestamp host logger_timestamp` (new
    loggers) or `host timestamp` (older ones, e.g. intel's `nohost 0`)."""
    if len(tokens) < 3:
        ctx.reject("PARAM needs a name and a value: PARAM name value [" + TRAILER + "]", number)
        return
    if len(tokens) >= 6 and is_decimal(tokens[-3]) and is_decimal(tokens[-1]):
        value = " ".join(tokens[2:-3])
    elif len(tokens) == 5 and not is_decimal(tokens[3]) and is_decimal(tokens[4]):
        value = tokens[2]
    else:
        value = " ".join(tokens[2:])
    raw.params[tokens[1]] = (value, number)


# --------------------------------------------------------------------------------------------
# Message layouts and number parsing


class _Layout:
    """The fields of one message line, for saying which token is wrong and what was expected."""

    def __init__(self, name: str, fields: list[tuple[str, int | None]]):
        self.name = name
        self.fields = fields  # (label, how many); None: a count not yet known

    @property
    def expected(self) -> str:
        parts = [label if count == 1 else f"{'n' if count is None else count} {label}s"
                 for label, count in self.fields]  # fmt: skip
        return f"expected {self.name} " + " ".join(parts)

    def describe(self, index: int) -> str:
        """The field at token `index` (0 is the message name)."""
        position = index - 1
        for label, count in self.fields:
            if count is None:  # fields after an unknown count cannot be located
                break
            if position < count:
                return f"{label} {position + 1} of {count}" if count != 1 else label
            position -= count
        return f"token {index + 1}"


def _pose_fields(prefix: str) -> list[tuple[str, int]]:
    return [(f"{prefix}_x", 1), (f"{prefix}_y", 1), (f"{prefix}_theta", 1)]


_TRAILER_FIELDS = [("ipc_timestamp", 1), ("ipc_hostname", 1), ("logger_timestamp", 1)]
_CONFIG_FIELDS = [
    (label, 1)
    for label in (
        "laser_type", "start_angle", "field_of_view", "angular_resolution", "maximum_range",
        "accuracy", "remission_mode",
    )
]  # fmt: skip
_MOTION_FIELDS = [
    (label, 1)
    for label in ("tv", "rv", "forward_safety_dist", "side_safety_dist", "turn_axis")
]


# Below this many tokens, Python's float() beats numpy's per-call overhead.
_SHORT = 16


def _floats(tokens: list[str], start: int, stop: int, layout: _Layout) -> np.ndarray:
    """tokens[start:stop] as finite float64; a bad token is reported by its field name."""
    try:
        if stop - start <= _SHORT:
            values = np.array([float(t) for t in tokens[start:stop]])
        else:
            values = np.array(tokens[start:stop], dtype=np.float64)
        # float() and numpy also read "1_0" as 10 and non-ASCII digits; checked on the joined
        # text, so that a good line costs no loop over its tokens in Python.
        text = " ".join(tokens[start:stop])
        if np.isfinite(values).all() and "_" not in text and text.isascii():
            return values
    except ValueError:
        pass
    for index in range(start, stop):
        if not is_decimal(tokens[index]):
            raise _Malformed(
                f"{layout.describe(index)} is {quote(tokens[index])}, not a finite decimal number; "
                f"{layout.expected}"
            )
    raise AssertionError("unreachable: some token failed to parse")


def _count(tokens: list[str], index: int, what: str, layout: _Layout, minimum: int = 0) -> int:
    """A whole number >= minimum (a beam or remission count) at token `index`."""
    if index >= len(tokens):
        raise _Malformed(f"the line ends before {what}; {layout.expected}")
    token = tokens[index]
    if not (token.isascii() and token.isdigit()) or int(token) < minimum:
        raise _Malformed(
            f"{what} is {quote(token)}, not a whole number >= {minimum}; {layout.expected}"
        )
    return int(token)


def _timestamp(tokens: list[str], layout: _Layout) -> float:
    """The ipc timestamp; the logger timestamp is checked but not kept."""
    stamp, logger_stamp = tokens[-3], tokens[-1]
    if not is_decimal(stamp):
        raise _Malformed(f"ipc_timestamp is {quote(stamp)}, not a finite decimal number; {layout.expected}")
    if not is_decimal(logger_stamp):
        raise _Malformed(
            f"logger_timestamp is {quote(logger_stamp)}, not a finite decimal number; {layout.expected}"
        )
    seconds = float(stamp)
    if abs(seconds) > MAX_TIMESTAMP:
        raise _Malformed(f"ipc_timestamp {seconds:g} is beyond ±{MAX_TIMESTAMP:g} s: CARMEN timestamps are seconds")
    return seconds


# --------------------------------------------------------------------------------------------
# Messages


@dataclass
class _Scan:
    """One parsed laser message."""

    line: int
    stamp: float
    ranges: np.ndarray  # (n,) float64, as logged
    remissions: np.ndarray | None = None
    laser_pose: np.ndarray | None = None
    robot_pose: np.ndarray | None = None
    geometry: tuple[float, float, float] | None = None  # start_angle, resolution, max range


_ODOM_LAYOUT = _Layout(
    "ODOM", [(label, 1) for label in ("x", "y", "theta", "tv", "rv", "accel")] + _TRAILER_FIELDS
)


def _parse_odom(tokens: list[str]) -> tuple[float, np.ndarray]:
    if len(tokens) != 10:
        raise _Malformed(f"ODOM has {len(tokens) - 1} values, not 9; {_ODOM_LAYOUT.expected}")
    values = _floats(tokens, 1, 7, _ODOM_LAYOUT)
    return _timestamp(tokens, _ODOM_LAYOUT), _near(values[:3], "")


def _near(pose: np.ndarray, prefix: str) -> np.ndarray:
    """`pose` (x, y, theta), logged as the fields `prefix`x, `prefix`y, `prefix`theta, checked
    to lie within ±MAX_POSITION and to turn within ±MAX_HEADING."""
    if np.abs(pose[:2]).max() > MAX_POSITION:
        raise _Malformed(f"{prefix}x, {prefix}y = {pose[0]:.6g}, {pose[1]:.6g} m lie beyond ±{MAX_POSITION:g} m, "
                         "where no robot drives")
    # Headings are read unwrapped (some loggers add up the turns), but beyond MAX_HEADING (1e6 rad,
    # 160 000 turns) they come from a broken logger, and wrapped they give any angle at all.
    if abs(pose[2]) > MAX_HEADING:
        raise _Malformed(f"{prefix}theta = {pose[2]:.6g} rad lies beyond ±{MAX_HEADING:g} rad, more turns than "
                         "any robot makes")
    return pose


def _old_laser_fields(n: int | None) -> list[tuple[str, int | None]]:
    poses = [*_pose_fields("laser"), *_pose_fields("odom")]
    return [("num_readings", 1), ("range", n), *poses, *_TRAILER_FIELDS]


def _parse_old_laser(tokens: list[str]) -> _Scan:
    """FLASER / RLASER n ranges.. laser_pose robot_pose <trailer>."""
    name = tokens[0]
    layout = _Layout(name, _old_laser_fields(None))
    n = _count(tokens, 1, "num_readings", layout, minimum=1)
    layout.fields = _old_laser_fields(n)
    after = len(tokens) - 2
    if after != n + 9:
        raise _Malformed(
            f"{name} declares {n} ranges but {after} values follow the count "
            f"(room for {after - 9} ranges); expected {n} ranges + 6 pose values + {TRAILER}"
        )
    values = _floats(tokens, 2, n + 8, layout)
    return _Scan(
        line=0,
        stamp=_timestamp(tokens, layout),
        ranges=values[:n],
        laser_pose=_near(values[n : n + 3], "laser_"),
        robot_pose=_near(values[n + 3 : n + 6], "odom_"),
    )


def _parse_new_laser(tokens: list[str], with_pose: bool) -> _Scan:
    """ROBOTLASERk (with_pose) or RAWLASERk: config, ranges, remissions[, poses, motion]."""
    name = tokens[0]
    tail = [*_pose_fields("laser"), *_pose_fields("robot"), *_MOTION_FIELDS] if with_pose else []
    layout = _Layout(name, [*_CONFIG_FIELDS, ("num_readings", 1), ("range", None)])
    n = _count(tokens, 8, "num_readings", layout, minimum=1)
    layout.fields = [*_CONFIG_FIELDS, ("num_readings", 1), ("range", n), ("num_remissions", 1)]
    m = _count(tokens, 9 + n, f"num_remissions (the token after {n} ranges)", layout)
    layout.fields += [("remission", m), *tail, *_TRAILER_FIELDS]
    total = 10 + n + m + len(tail) + 3
    if len(tokens) != total:
        parts = "6 pose values, 5 motion values, " if with_pose else ""
        raise _Malformed(
            f"{name} declares {n} ranges and {m} remissions, so the line should have {total} "
            f"tokens but it has {len(tokens)}; expected {name}, 7 config values, "
            f"num_readings, {n} ranges, num_remissions, {m} remissions, {parts}{TRAILER}"
        )
    config = _floats(tokens, 1, 8, layout)
    ranges = _floats(tokens, 9, 9 + n, layout)
    remissions = _floats(tokens, 10 + n, 10 + n + m, layout)
    start, resolution, max_range = config[1], config[3], config[4]
    if not max_range > 0.0:
        raise _Malformed(f"maximum_range is {tokens[5]!r}; it must be positive")
    if n > 1 and abs(resolution) < MIN_BEAM_STEP:
        raise _Malformed(
            f"angular_resolution is {tokens[4]!r}: it would put all {n} beams at one angle "
            f"(field_of_view is {tokens[3]!r})"
        )
    last = start + max(n - 1, 0) * resolution
    if not (abs(start) <= MAX_BEAM_ANGLE and abs(last) <= MAX_BEAM_ANGLE):
        raise _Malformed(
            f"start_angle {tokens[2]!r} and angular_resolution {tokens[4]!r} put the beams at "
            f"{start:.6g} .. {last:.6g} rad; a laser's beams lie within ±2π"
        )
    scan = _Scan(
        line=0,
        stamp=_timestamp(tokens, layout),
        ranges=ranges,
        remissions=remissions if m == n else None,
        geometry=(float(start), float(resolution), float(max_range)),
    )
    if with_pose:
        poses = _floats(tokens, 10 + n + m, 21 + n + m, layout)  # with tv, rv, safety, turn
        scan.laser_pose, scan.robot_pose = _near(poses[:3], "laser_"), _near(poses[3:6], "robot_")
    return scan


def _parse_laser(kind: str, tokens: list[str]) -> _Scan:
    if kind in ("FLASER", "RLASER"):
        return _parse_old_laser(tokens)
    return _parse_new_laser(tokens, with_pose=kind.startswith("ROBOTLASER"))


def _parse_odometry(ctx: _Context, lines: list[tuple[int, str]]) -> tuple[Trajectory, np.ndarray]:
    """All ODOM messages as a Trajectory (file order), and their line numbers."""
    stamps: list[float] = []
    poses: list[np.ndarray] = []
    numbers: list[int] = []
    for number, text in lines:
        try:
            stamp, pose = _parse_odom(text.split())
        except _Malformed as exc:
            ctx.reject(str(exc), number)
            continue
        stamps.append(stamp)
        poses.append(pose)
        numbers.append(number)
    trajectory = Trajectory(np.array(stamps), np.array(poses).reshape(-1, 3))
    return trajectory, np.array(numbers, dtype=np.int64)


def _choose_kind(ctx: _Context, raw: _RawLog, laser: str) -> str:
    """The message kind that gives the scans; the laser's other kinds count as ignored."""
    old, new, bare = _KINDS[laser]
    present = [kind for kind in (old, new, bare) if raw.lasers.get(kind)]
    if old in present and new in present:
        raise ctx.error(
            f"the {laser} laser is logged both as {old} (first at line {raw.lasers[old][0][0]}) "
            f"and as {new} (first at line {raw.lasers[new][0][0]}); cannot tell which to use"
        )
    if not present:
        raise ctx.error(f"no {laser} laser scans in the log ({old}, {new} or {bare} messages)")
    chosen = present[0]  # with poses first: old or new, else the bare RAWLASER
    for kind in present[1:]:
        raw.ignored[kind] += len(raw.lasers[kind])
    return chosen


def _parse_scans(ctx: _Context, kind: str, lines: list[tuple[int, str]]) -> list[_Scan]:
    """Parse the chosen laser's lines (each with its own beam count and geometry)."""
    scans: list[_Scan] = []
    for number, text in lines:
        try:
            scan = _parse_laser(kind, text.split())
        except _Malformed as exc:
            ctx.reject(str(exc), number)
            continue
        scan.line = number
        scans.append(scan)
    if not scans:
        raise ctx.error(f"no well-formed {kind} scan in the log")
    return scans


# --------------------------------------------------------------------------------------------
# Building the ScanSequence


def _build_sequence(
    ctx: _Context,
    kind: str,
    laser: str,
    scans: list[_Scan],
    params: dict[str, tuple[str, int]],
    odometry: Trajectory,
    odom_lines: np.ndarray,
    fov_deg: float,
) -> ScanSequence:
    counts = np.array([len(s.ranges) for s in scans])
    stamps = np.array([s.stamp for s in scans])
    raw = pad_rows([s.ranges for s in scans], np.inf, np.float64)  # padding: no echo
    if scans[0].geometry is not None:
        starts, steps, max_ranges = np.array([s.geometry for s in scans]).T
        max_range, rule = float(max_ranges.max()), f"{kind} maximum_range field"
        if max_ranges.min() < max_range:
            rule += f" ({max_ranges.min():g} to {max_range:g} m)"
        no_echo = max_ranges[:, None]  # each scan its own
    else:
        fov = math.radians(_fov_deg(ctx, laser, params, fov_deg))
        starts = np.full(len(scans), -0.5 * fov)  # as old_format_angles, each scan its count
        steps = _old_format_step(counts, fov)
        max_range, rule = _old_format_max_range(ctx, laser, params, raw)
        no_echo = max_range
    ranges = _no_echo_to_inf(raw, no_echo)
    _check_some_reading(ctx, kind, raw, ranges, counts, max_range)
    angles, beam_counts = evenly_spaced_beams(starts, steps, counts, tolerance=GEOMETRY_TOLERANCE)
    odometry_rule = f"the {kind} messages' robot poses"
    if scans[0].robot_pose is not None:
        robot_poses = np.array([s.robot_pose for s in scans])
        laser_poses = np.array([s.laser_pose for s in scans])
        sensor_pose = _sensor_pose(ctx, kind, laser, scans, laser_poses, robot_poses, params)
        distinct, distinct_lines = _without_repeats(odometry, odom_lines)
        held = _held_odometry(scans, robot_poses, distinct, distinct_lines)
        if held is not None:
            robot_poses, odometry_rule = _unhold_odometry(
                ctx, kind, stamps, np.array([s.line for s in scans]), robot_poses, distinct, distinct_lines, held
            )
    else:
        odometry_rule = "interpolated from ODOM at each scan's timestamp"
        robot_poses = _interpolate_odometry(ctx, kind, scans, stamps, odometry, odom_lines)
        sensor_pose = _param_sensor_pose(ctx, laser, params)
        if sensor_pose is None:
            sensor_pose = np.zeros(3)
    return ScanSequence(
        timestamps=stamps,
        ranges=ranges,
        angles=angles,
        odometry=robot_poses,
        sensor_pose=sensor_pose,
        max_range=float(max_range),
        remissions=_remissions(scans),
        source=str(ctx.path),
        beam_counts=beam_counts,
        max_range_rule=rule,
        odometry_rule=odometry_rule,
    )


def _check_some_reading(ctx: _Context, kind: str, raw: np.ndarray, ranges: np.ndarray, counts: np.ndarray,
                        max_range: float) -> None:
    """Refuse a log without an echo whose readings are 0 m or less, which a laser logs for no
    reading, naming them: the later no-echo message would call them beams that saw nothing
    within the maximum range."""
    if np.isfinite(ranges).any():
        return
    logged = raw[np.arange(raw.shape[1]) < counts[:, None]]  # not the padding
    unread = logged[logged <= 0.0]
    if not unread.size:
        return
    lo, hi = float(unread.min()), float(unread.max())
    what = f"{lo:g} m" if lo == hi else f"0 m or less ({lo:g} to {hi:g} m)"
    scans = f"the {len(counts)} {kind} scans"
    if unread.size == logged.size:
        raise ctx.error(f"every one of the {logged.size} readings of {scans} is {what}, which is no reading: there "
                        "is nothing to map")
    raise ctx.error(f"no reading of {scans} is an echo: {unread.size} of the {logged.size} are {what}, which is no "
                    f"reading, and the other {logged.size - unread.size} lie at or beyond the maximum range "
                    f"{max_range:g} m: there is nothing to map")


def old_format_angles(n_beams: int, fov_deg: float) -> np.ndarray:
    """Beam angles (radians) of an old-format scan: CARMEN's convention, see read_carmen.

    The sweep spans [-fov/2, +fov/2] with a beam at each end; an even count means the last beam
    was dropped (CARMEN: "179 degrees (last beam ignored)" for 180 beams), an odd count keeps
    both ends. So 180 beams over 180° are -90°, -89°, ..., +89°.
    """
    fov = math.radians(fov_deg)
    return -0.5 * fov + _old_format_step(n_beams, fov) * np.arange(n_beams)


def _old_format_step(n_beams: int | np.ndarray, fov: float) -> float | np.ndarray:
    """The beam step (rad) of old-format scans of `n_beams` over `fov` rad (see above)."""
    gaps = np.where(np.asarray(n_beams) % 2 == 0, n_beams, np.maximum(np.asarray(n_beams) - 1, 1))
    return fov / gaps


def _param_float(ctx: _Context, params: dict[str, tuple[str, int]], name: str) -> float | None:
    if name not in params:
        return None
    value, line = params[name]
    if not is_decimal(value):
        raise ctx.error(f"PARAM {name} is {quote(value)}, not a finite decimal number", line)
    return float(value)


def _fov_deg(
    ctx: _Context, laser: str, params: dict[str, tuple[str, int]], default: float
) -> float:
    name = f"laser_{laser}_laser_fov"
    fov = _param_float(ctx, params, name)
    if fov is None:
        return default
    if not (0.0 < fov <= 360.0):
        raise ctx.error(f"PARAM {name} is {fov}; expected degrees in (0, 360]", params[name][1])
    return fov


def _old_format_max_range(
    ctx: _Context, laser: str, params: dict[str, tuple[str, int]], ranges: np.ndarray
) -> tuple[float, str]:
    """(maximum range, the rule that gave it) of old-format scans: a PARAM, else a no-echo code
    found in the readings, else the default."""
    for name in (f"robot_{laser}_laser_max", f"laser_{laser}_laser_max_range"):
        value = _param_float(ctx, params, name)
        if value is not None:
            if value <= 0.0:
                raise ctx.error(f"PARAM {name} is {value}; it must be positive", params[name][1])
            return value, f"PARAM {name} = {value:g}"
    top = repeated_top_value(ranges[np.isfinite(ranges)])
    if top is not None:
        value, count = top
        warnings.warn(
            f"{ctx.path}: {count} readings of exactly {_logged_metres(value)} m, the largest below "
            f"{DEFAULT_MAX_RANGE:g} m, are taken for the laser's no-echo value (the log states no "
            f"maximum range; PARAM robot_{laser}_laser_max would)",
            CarmenWarning,
            stacklevel=4,
        )
        return value, f"repeated top value {_logged_metres(value)} m ({count} readings)"
    beyond = int(np.count_nonzero(ranges >= DEFAULT_MAX_RANGE))
    return DEFAULT_MAX_RANGE, f"default {DEFAULT_MAX_RANGE:g} m ({beyond} readings at or beyond it)"


def _logged_metres(value: float) -> str:
    """A reading as the log holds it: to the centimetre, as CARMEN writes ranges, or with every
    digit it has beyond that (readings of 0.001 m printed as "0.00 m" read as zeros)."""
    return f"{value:.2f}" if round(value, 2) == value else repr(float(value))


def repeated_top_value(readings: np.ndarray) -> tuple[float, int] | None:
    """(value, count) of a laser's own no-echo code among `readings`, or None.

    A laser that saw nothing reports a fixed value: SICK's codes (81.83, 81.91 m) lie above the
    80 m default, but a driver may log its range limit instead (one log holds 11,139 readings of
    exactly 50.00 m). Such a code is one exact value at the very top of the readings, repeated far
    more often than any real distance: walls spread over many values (noise, the 1 cm print
    resolution), a code does not. So the largest reading below the default counts as the code
    when it holds at least TOP_VALUE_SHARE of all readings and TOP_VALUE_MIN_COUNT of them, and
    at least TOP_VALUE_DOMINANCE times as many as any other value within TOP_VALUE_BAND below it.
    A wall that is merely the farthest thing seen fails the count; a range limit that readings
    pile up against without a code fails the dominance test.
    """
    below = readings[(readings > 0.0) & (readings < DEFAULT_MAX_RANGE)]
    if below.size == 0:
        return None
    top = below.max()
    count = int(np.count_nonzero(below == top))
    if count < max(TOP_VALUE_MIN_COUNT, TOP_VALUE_SHARE * readings.size):
        return None
    near = below[(below >= top * (1.0 - TOP_VALUE_BAND)) & (below < top)]
    runner_up = int(np.unique(near, return_counts=True)[1].max(initial=0))
    if count < TOP_VALUE_DOMINANCE * runner_up:
        return None
    return float(top), count


def _no_echo_to_inf(ranges: np.ndarray, max_range: float | np.ndarray) -> np.ndarray:
    """float32 ranges with +inf where the laser saw nothing (>= max range, or <= 0). A reading
    beyond float32 (3.4e38 m) becomes +inf too: no sensor measures that far; one too small for
    float32 (below 1e-45 m, which rounds to 0) is no reading either."""
    with np.errstate(over="ignore", under="ignore"):
        out = ranges.astype(np.float32)
        top = np.asarray(max_range, dtype=np.float64).astype(np.float32)
    # Both sides in float32: a reading just below the maximum that rounds to it is no echo too.
    out[(out >= top) | (out <= 0.0)] = np.inf
    return out


def _remissions(scans: list[_Scan]) -> np.ndarray | None:
    """Remissions only if every scan has one per beam (padded with 0 like its ranges)."""
    if any(s.remissions is None for s in scans):
        return None
    with np.errstate(over="ignore"):  # a remission beyond float32 becomes +inf
        return pad_rows([s.remissions for s in scans], 0.0, np.float32)


def _param_sensor_pose(
    ctx: _Context, laser: str, params: dict[str, tuple[str, int]]
) -> np.ndarray | None:
    """robot_T_sensor from the offset PARAMs, or None if the log has none of them."""
    names = [f"robot_{laser}laser_{what}" for what in ("offset", "side_offset", "angular_offset")]
    offset, side, angle = (_param_float(ctx, params, name) for name in names)
    if offset is None and side is None and angle is None:
        return None
    pose = np.array([offset or 0.0, side or 0.0, angle or 0.0])
    if math.hypot(pose[0], pose[1]) > MAX_MOUNT:
        name = names[0] if offset is not None else names[1]
        raise ctx.error(f"PARAM {name} puts the {laser} laser {math.hypot(pose[0], pose[1]):.6g} m from the "
                        f"robot's centre; a laser on the robot is within {MAX_MOUNT:g} m of it (in metres)",
                        params[name][1])
    if abs(pose[2]) > MAX_HEADING:
        raise ctx.error(f"PARAM {names[2]} is {pose[2]:.6g} rad, beyond ±{MAX_HEADING:g} rad: no mount turns "
                        "the laser so far", params[names[2]][1])
    if laser == "rear" and angle is None:
        # Older CARMEN knew only robot_rearlaser_offset and mounted the rear laser facing
        # backwards, the offset measured along its own heading (localize: theta + pi).
        pose = np.array([0.0 - pose[0], 0.0 - pose[1], math.pi])
    return pose


def _sensor_pose(
    ctx: _Context,
    kind: str,
    laser: str,
    scans: list[_Scan],
    laser_poses: np.ndarray,
    robot_poses: np.ndarray,
    params: dict[str, tuple[str, int]],
) -> np.ndarray:
    """robot_T_sensor from the messages' poses if they differ by one fixed offset, else from
    PARAMs (else zero).

    A few laser poses off the mount (a glitch in the logger; at most 1 - MOUNT_MIN_SHARE of the
    scans) do not hide it: the mount is then the median offset, and a CarmenWarning names the
    first line that departs. Laser poses that are no fixed offset from the robot poses are
    another trajectory, not a mount: a corrected log (GMapping's `.gfs.log`, the benchmark
    sites' `corrected` logs) puts a SLAM solution there beside the raw odometry. The log is read
    all the same (its scans and odometry are what SLAM needs), the laser poses are left out, and
    a CarmenWarning says so.
    """
    from_params = _param_sensor_pose(ctx, laser, params)
    fallback = np.zeros(3) if from_params is None else from_params
    if np.array_equal(laser_poses, robot_poses):
        # Loggers that know no offset copy the robot pose; that says nothing about the mount.
        return fallback
    offsets = relative(robot_poses, laser_poses)
    first = offsets[0]
    if not np.all(_same_offset(offsets, first)):
        median = _median_offset(offsets)
        departs = np.flatnonzero(~_same_offset(offsets, median))
        if departs.size == 0:  # a mount that wavers within the tolerance: its median
            first = median
        elif len(offsets) - departs.size >= MOUNT_MIN_SHARE * len(offsets) - 1e-9:
            i = int(departs[0])
            warnings.warn(
                f"{ctx.path}: {departs.size} of {len(offsets)} {kind} laser poses depart from "
                f"the laser's mount on the robot, {_fmt_pose(median)} (the median), first at "
                f"line {scans[i].line} at {_fmt_pose(offsets[i])}; the mount is the median",
                CarmenWarning,
                stacklevel=4,
            )
            first = median
        else:
            change = relative(first[None, :], offsets)
            worst = int(np.argmax(np.hypot(change[:, 0], change[:, 1]) + np.abs(change[:, 2])))
            i = int(np.flatnonzero(~_same_offset(offsets, offsets[0]))[0])
            source = "the PARAMs'" if from_params is not None else "none, as no PARAM gives one"
            warnings.warn(
                f"{ctx.path}: the {kind} laser poses are no fixed mount on the robot poses: "
                f"{_fmt_pose(first)} in the robot's frame in the first scan (line {scans[0].line}), "
                f"{_fmt_pose(offsets[i])} at line {scans[i].line}, {_fmt_pose(offsets[worst])} at line "
                f"{scans[worst].line} (a corrected log, such as GMapping's .gfs.log, holds a SLAM "
                f"solution there); they are left out, the robot poses are the odometry, and the "
                f"laser's mount is {source} {_fmt_pose(fallback)}",
                CarmenWarning,
                stacklevel=4,
            )
            return fallback
    if math.hypot(first[0], first[1]) > MAX_MOUNT:
        raise ctx.error(f"the {kind} laser poses lie {math.hypot(first[0], first[1]):.6g} m from the robot poses, "
                        f"one fixed offset; a laser on the robot is within {MAX_MOUNT:g} m of it", scans[0].line)
    if from_params is not None and not _same_offset(from_params[None, :], first)[0]:
        warnings.warn(
            f"{ctx.path}: the PARAMs put the {laser} laser at {_fmt_pose(from_params)} on the "
            f"robot but the {kind} messages at {_fmt_pose(first)}; using the messages",
            CarmenWarning,
            stacklevel=4,
        )
    return first


def _median_offset(offsets: np.ndarray) -> np.ndarray:
    """The per-axis median of (x, y, theta) offsets; theta's about the first, so wrap is no jump."""
    turn = np.median(wrap_angle(offsets[:, 2] - offsets[0, 2]))
    return np.array([np.median(offsets[:, 0]), np.median(offsets[:, 1]), wrap_angle(offsets[0, 2] + turn)])


def _same_offset(offsets: np.ndarray, reference: np.ndarray) -> np.ndarray:
    shift = np.hypot(offsets[:, 0] - reference[0], offsets[:, 1] - reference[1])
    turn = np.abs(wrap_angle(offsets[:, 2] - reference[2]))
    return (shift <= OFFSET_TOLERANCE_M) & (turn <= OFFSET_TOLERANCE_RAD)


def _fixed(value: float, decimals: int) -> str:
    """`value` with `decimals` decimals, as a log writes it; in exponent form where that would
    print hundreds of digits (a pose or stamp of 1e300 read from a broken line)."""
    return f"{value:.{decimals}f}" if abs(value) < 1e12 else f"{value:.6g}"


def _fmt_pose(pose: np.ndarray) -> str:
    return f"(x {_fixed(pose[0], 4)} m, y {_fixed(pose[1], 4)} m, theta {_fixed(math.degrees(pose[2]), 2)}°)"


def _interpolate_odometry(
    ctx: _Context,
    kind: str,
    scans: list[_Scan],
    stamps: np.ndarray,
    odometry: Trajectory,
    odom_lines: np.ndarray,
) -> np.ndarray:
    """Robot poses at `stamps` from ODOM: linear in x, y; along the shorter arc in theta."""
    if len(odometry) == 0:
        raise ctx.error(f"{kind} scans carry no pose and the log has no ODOM message")
    t = odometry.timestamps
    backwards = np.flatnonzero(np.diff(t) < 0)
    if backwards.size:
        raise ctx.error(
            f"cannot interpolate {kind} poses: ODOM timestamps go backwards here",
            int(odom_lines[backwards[0] + 1]),
        )
    outside = np.flatnonzero((stamps < t[0]) | (stamps > t[-1]))
    if outside.size:
        i = int(outside[0])
        raise ctx.error(
            f"{kind} scan at t = {_fixed(stamps[i], 6)} is outside the odometry's time span "
            f"[{_fixed(t[0], 6)}, {_fixed(t[-1], 6)}]; its pose cannot be interpolated",
            scans[i].line,
        )
    poses = odometry.poses
    theta = np.unwrap(poses[:, 2])  # consecutive steps below pi: the shorter arc
    return np.stack(
        [
            np.interp(stamps, t, poses[:, 0]),
            np.interp(stamps, t, poses[:, 1]),
            wrap_angle(np.interp(stamps, t, theta)),
        ],
        axis=1,
    )


def _without_repeats(odometry: Trajectory, odom_lines: np.ndarray) -> tuple[Trajectory, np.ndarray]:
    """The ODOM messages and their lines without exact repeats of the message before (same
    stamp and pose: some loggers write each line twice), which would hide the motion."""
    t, poses = odometry.timestamps, odometry.poses
    keep = np.r_[True, (np.diff(t) != 0) | np.any(np.diff(poses, axis=0) != 0, axis=1)][: len(t)]
    return Trajectory(t[keep], poses[keep]), odom_lines[keep]


def _held_odometry(
    scans: list[_Scan], robot_poses: np.ndarray, odometry: Trajectory, odom_lines: np.ndarray
) -> np.ndarray | None:
    """For a log whose laser messages carry the pose of the last ODOM message before them
    (sample-and-hold, as in the ACES and Intel logs) rather than the pose at the scan's time
    (Freiburg 079's are interpolated to it): the index of that ODOM message per scan (-1 before
    the first one). Else None. `odometry`: the ODOM messages without repeats (_without_repeats).

    Judged on the scans taken while the odometry moved (the ODOM message after the scan's last
    one has another pose), where a pose interpolated to the scan's time would differ from the
    last ODOM pose: at least HELD_MIN_SCANS of them, HELD_MIN_SHARE of which equal it to
    HELD_POSE_TOLERANCE, taken in at least HELD_MIN_INTERVALS intervals between ODOM messages,
    with ODOM messages older than their scans by more than HELD_MIN_AGE in more than
    HELD_OLD_SHARE of them.
    """
    if len(odometry) < 2:
        return None
    t, poses = odometry.timestamps, odometry.poses
    lines = np.array([s.line for s in scans])
    last = np.searchsorted(odom_lines, lines) - 1  # the last ODOM line before each scan's line
    judged = np.flatnonzero((last >= 0) & (last + 1 < len(t)))
    judged = judged[np.any(poses[last[judged] + 1] != poses[last[judged]], axis=1)]
    if len(judged) < HELD_MIN_SCANS or len(np.unique(last[judged])) < HELD_MIN_INTERVALS:
        return None
    difference = robot_poses[judged] - poses[last[judged]]
    difference[:, 2] = wrap_angle(difference[:, 2])
    equal = np.all(np.abs(difference) <= HELD_POSE_TOLERANCE, axis=1)
    if np.mean(equal) < HELD_MIN_SHARE:
        return None
    # An ODOM message stamped with its scan (as write_carmen writes them) is not old.
    ages = np.array([s.stamp for s in scans])[judged] - t[last[judged]]
    old_enough = np.percentile(ages, 100.0 * (1.0 - HELD_OLD_SHARE)) > HELD_MIN_AGE
    return last if old_enough else None


def _unhold_odometry(
    ctx: _Context, kind: str, stamps: np.ndarray, scan_lines: np.ndarray, robot_poses: np.ndarray,
    odometry: Trajectory, odom_lines: np.ndarray, held: np.ndarray,
) -> tuple[np.ndarray, str]:
    """Held odometry (see _held_odometry) made into the pose at each scan's timestamp, and the
    rule that says so: interpolated from the ODOM messages (`interpolate_poses`, as for a ROS
    bag) at the scan's stamp, clamped to the stamps of the ODOM messages one beyond the two
    around the scan in the file. Loggers write messages in the order they arrive, which may
    differ from their stamps' (in ACES, 157 scans are stamped up to 0.11 s before the ODOM
    message written before them); a scan stamp that jitters further cannot move its scan
    further.

    A held pose is as old as the time since its ODOM message: in the ACES log a median 0.11 s
    (95th percentile 0.20 s), 4° of heading when the robot turns at 0.6 rad/s, and varying from
    scan to scan, which no constant scan delay (omnitof.slam.timing) can undo. An ODOM message
    whose stamp leaves its neighbours' order (a line out of place) is left out. Where the stamps
    still go backwards after that (Intel's: 602 backward steps, 371 of them such single lines),
    the clock is too unsteady to interpolate by and every pose stays as logged, with a warning if
    they are a median HELD_STALE_WARNING old or more (Intel's are a median 0.26 ms old, 95th
    percentile 0.14 s: no warning). Scans before the first or after the last ODOM message keep
    their logged pose.
    """
    t, poses = odometry.timestamps, odometry.poses
    has = held >= 0
    ages = stamps[has] - t[held[has]]
    age = f"median {np.median(ages):.3f} s, 95th percentile {np.percentile(ages, 95):.3f} s"
    stray = np.zeros(len(t), dtype=bool)
    stray[1:-1] = (t[:-2] <= t[2:]) & ((t[1:-1] < t[:-2]) | (t[1:-1] > t[2:]))
    t, poses, odom_lines = t[~stray], poses[~stray], odom_lines[~stray]
    if np.any(np.diff(t) < 0):
        if np.median(ages) >= HELD_STALE_WARNING:
            warnings.warn(
                f"{ctx.path}: each {kind} message carries the last ODOM pose before it ({age} "
                "old), but the ODOM timestamps go backwards, so the poses cannot be interpolated "
                "to the scans' timestamps and are used as logged; expect a lag in turns",
                CarmenWarning,
                stacklevel=4,
            )
        return robot_poses, (
            f"the {kind} messages' robot poses, each the last ODOM pose before it ({age} old): "
            "ODOM timestamps go backwards, so they were not interpolated to the scans' timestamps"
        )
    n = len(t)
    after = np.searchsorted(odom_lines, scan_lines)  # the first ODOM line after each scan's line
    lo, hi = np.clip(after - 2, 0, n - 1), np.clip(after + 1, 0, n - 1)
    tau = np.clip(stamps, t[lo], t[hi])
    interpolated = interpolate_poses(Trajectory(t, poses), tau)
    inside = (after >= 1) & (after < n) & np.all(np.isfinite(interpolated), axis=1)
    out = np.where(inside[:, None], interpolated, robot_poses)
    rule = f"interpolated from ODOM at each scan's timestamp: the {kind} messages carry the last ODOM pose ({age} old)"
    clamped = int(np.sum(inside & (tau != stamps)))
    if clamped:
        rule += f"; scans stamped beyond the ODOM messages around them, clamped to theirs: {clamped}"
    if not inside.all():
        rule += f"; scans with no ODOM span around them, kept as logged: {int(np.sum(~inside))}"
    if stray.any():
        rule += f"; ODOM lines stamped out of order, left out: {int(stray.sum())}"
    warnings.warn(
        f"{ctx.path}: each {kind} message carries the last ODOM pose before it ({age} old), so "
        "each scan's odometry is interpolated from the ODOM messages at the scan's timestamp",
        CarmenWarning,
        stacklevel=4,
    )
    return out, rule


def _check_time_order(
    ctx: _Context, kind: str, scans: list[_Scan], max_time_reversal: float
) -> int:
    """Count backward timestamp steps; refuse one larger than max_time_reversal."""
    stamps = np.array([s.stamp for s in scans])
    steps = np.diff(stamps)
    backwards = np.flatnonzero(steps < 0)
    if not backwards.size:
        return 0
    too_far = backwards[-steps[backwards] > max_time_reversal]
    if too_far.size:
        i = int(too_far[0]) + 1
        # What to do differs: one stamp written wrong is a line to mend; a clock set back is a
        # log of two runs.
        if i >= 2 and stamps[i - 2] <= stamps[i] + max_time_reversal:
            advice = (f"line {scans[i - 1].line}'s stamp lies ahead of the scans on both sides of it: correct or "
                      "delete that line")
        else:
            advice = f"the clock was set back: split the log before line {scans[i].line} and map each part"
        raise ctx.error(
            f"{kind} timestamps go backwards: {_fixed(stamps[i], 6)} follows {_fixed(stamps[i - 1], 6)} "
            f"(line {scans[i - 1].line}), {_fixed(stamps[i - 1] - stamps[i], 6)} s earlier; at most "
            f"{max_time_reversal} s is tolerated; {advice}",
            scans[i].line,
        )
    first = int(backwards[0]) + 1
    warnings.warn(
        f"{ctx.path}: {backwards.size} {kind} timestamps are earlier than the one before "
        f"(by up to {-steps.min():.3f} s; first at line {scans[first].line}); the scans are kept "
        "in file order with their logged timestamps",
        CarmenWarning,
        stacklevel=3,
    )
    return int(backwards.size)


# --------------------------------------------------------------------------------------------
# Writing


def write_carmen(path: str | Path, scans: ScanSequence, *, hostname: str = "omnitof") -> None:
    """Write scans as a new-format CARMEN log (ROBOTLASER1 per scan, ODOM before each), so that
    other SLAM tools can read them; `read_carmen` reads it back to the same arrays (to the
    printed precision: 1 mm ranges, 1e-6 poses, microsecond timestamps), per-scan geometry too.

    Each scan's beams must be evenly spaced (ROBOTLASER1 states start angle and step only).
    No-echo readings (+inf, and NaN or 0 m or less, which read as no reading) are written as the
    maximum range. gzip or bzip2 compression follows the suffix
    (.gz, .bz2). The file is written atomically.

    Raises:
        ValueError: for what `read_carmen` would refuse, naming the argument or the scan: scans
            without odometry (`odometry_known` False), no scan, a scan without beams or with uneven ones, a hostname that is empty or holds
            whitespace, timestamps or poses that are not finite, a timestamp more than
            MAX_TIME_REVERSAL (1 s) before the one of the scan before, a max_range that is not a
            finite number of at least 1 mm and at most MAX_WRITTEN_RANGE (1000 km).
    """
    from omnitof.geometry import compose
    from omnitof.io.atomic import atomic_write

    if not scans.odometry_known:
        raise ValueError(
            "the scans have no odometry, and a CARMEN log holds one pose per scan: estimate it first "
            "(omnitof.slam.scan_odometry.with_scan_odometry) or write a LaserScan bag, which can be without"
        )
    _check_writable(scans, hostname)
    if scans.per_scan_geometry:
        geometry = [_robotlaser_geometry(scans.scan_angles(i), i) for i in range(len(scans))]
    else:
        geometry = [_robotlaser_geometry(scans.angles, None)] * len(scans)
    laser_poses = compose(scans.odometry, scans.sensor_pose)
    max_range = float(scans.max_range)
    # Readings of 0 m or less (to the millimetre written) read as no reading, and a log of
    # nothing else is refused (_check_some_reading): they are no echo, written as such.
    with np.errstate(invalid="ignore"):
        ranges = np.where(np.isfinite(scans.ranges) & (np.round(scans.ranges, 3) > 0.0), scans.ranges, max_range)
    header = (
        "# CARMEN Logfile written by omnitof\n"
        "# ODOM x y theta tv rv accel\n"
        "# ROBOTLASER1 laser_type start_angle field_of_view angular_resolution maximum_range "
        "accuracy remission_mode num_readings [range_readings] num_remissions [remissions] "
        "laser_pose_x laser_pose_y laser_pose_theta robot_pose_x robot_pose_y robot_pose_theta "
        "laser_tv laser_rv forward_safety_dist side_safty_dist turn_axis\n"
    )
    lines = [header]
    for i in range(len(scans)):
        t = scans.timestamps[i]
        o, lp = scans.odometry[i], laser_poses[i]
        start, step, n = geometry[i]
        fov = step * (n - 1)  # the span from the first to the last beam
        trailer = f"{t:.6f} {hostname} {t - scans.timestamps[0]:.6f}"
        lines.append(f"ODOM {o[0]:.6f} {o[1]:.6f} {o[2]:.6f} 0 0 0 {trailer}\n")
        r = " ".join(f"{v:.3f}" for v in ranges[i, :n])
        lines.append(
            f"ROBOTLASER1 0 {start:.17g} {fov:.17g} {step:.17g} {max_range:.3f} 0.01 0 "
            f"{n} {r} 0 {lp[0]:.6f} {lp[1]:.6f} {lp[2]:.6f} {o[0]:.6f} {o[1]:.6f} "
            f"{o[2]:.6f} 0 0 0 0 0 {trailer}\n"
        )
    text = "".join(lines).encode()
    suffix = Path(path).suffix
    if suffix == ".gz":
        text = gzip.compress(text)
    elif suffix == ".bz2":
        text = bz2.compress(text)
    with atomic_write(path, "wb") as f:
        f.write(text)


def _check_writable(scans: ScanSequence, hostname: str) -> None:
    """Refuse, before writing, what read_carmen would refuse to read back."""
    if not hostname or any(c.isspace() for c in hostname) or "\0" in hostname:
        # The hostname is one token of the line; a NUL makes the file binary to the reader.
        raise ValueError(f"hostname must be one word, without whitespace or NUL, got {hostname!r}")
    if len(scans) == 0:
        raise ValueError("no scans to write: a CARMEN log needs at least one")
    if not (math.isfinite(scans.max_range) and 0.0 < round(scans.max_range, 3) <= MAX_WRITTEN_RANGE):
        # Written to the millimetre: a smaller one would read as 0; no-echo readings are written
        # as it, in float32, where 1e300 is inf.
        raise ValueError(f"max_range must be a finite number of at least 1 mm and at most {MAX_WRITTEN_RANGE:g} m, "
                         f"got {scans.max_range}")
    i = first_non_finite(scans.timestamps, scans.odometry)
    if i is not None:
        raise ValueError(
            f"scan {i} is not finite: timestamp {scans.timestamps[i]}, odometry {scans.odometry[i].tolist()}"
        )
    if not np.isfinite(scans.sensor_pose).all():
        raise ValueError(f"sensor_pose is not finite: {scans.sensor_pose.tolist()}")
    for what, beyond, bound in (
        ("timestamp", np.abs(scans.timestamps) > MAX_TIMESTAMP, f"{MAX_TIMESTAMP:g} s"),
        ("position", np.abs(scans.odometry[:, :2]).max(axis=1) > MAX_POSITION, f"{MAX_POSITION:g} m"),
        ("heading", np.abs(scans.odometry[:, 2]) > MAX_HEADING, f"{MAX_HEADING:g} rad"),
    ):
        if beyond.any():
            i = int(np.flatnonzero(beyond)[0])
            raise ValueError(f"scan {i}: its {what} is beyond ±{bound}, which read_carmen refuses: timestamp "
                             f"{scans.timestamps[i]:g}, odometry {scans.odometry[i].tolist()}")
    steps = np.diff(scans.timestamps)
    back = np.flatnonzero(steps < -MAX_TIME_REVERSAL)
    if back.size:
        i = int(back[0]) + 1
        raise ValueError(
            f"scan {i}: its timestamp {scans.timestamps[i]:.6f} is {-steps[i - 1]:.6f} s before the "
            f"one of scan {i - 1}; read_carmen tolerates at most {MAX_TIME_REVERSAL} s"
        )


def _robotlaser_geometry(angles: np.ndarray, scan: int | None) -> tuple[float, float, int]:
    """(start_angle, angular_resolution, beams) of evenly spaced beams, else ValueError naming
    the scan (None: every scan's)."""
    if not len(angles):
        raise ValueError(f"{'the scans have' if scan is None else f'scan {scan} has'} no beam; ROBOTLASER1 needs one")
    step = float(angles[1] - angles[0]) if len(angles) > 1 else 0.0
    if len(angles) > 2 and not np.allclose(np.diff(angles), step, atol=1e-9):
        raise ValueError("ROBOTLASER1 needs evenly spaced beams")
    return float(angles[0]), step, len(angles)
