"""Laser-scan bags (`read_laserscan_bag`, `write_laserscan_bag`): planar scans and odometry.

ROS 1 (`.bag` files) or ROS 2 bags with sensor_msgs/LaserScan (or MultiEchoLaserScan, read as
each beam's first echo) and the robot's odometry
(nav_msgs/Odometry, or the transform odom → base on /tf where the robot publishes it only
there), read into a ScanSequence and written from one; `LaserTopics` names the topics and frames
where they are not found by type.

The static transform base_link → laser (tf2_msgs/TFMessage on /tf_static) carries the
ScanSequence's sensor_pose. Opening bags, the all-or-nothing write and the time conversions are
those of `omnitof.io.rosbag.common`. Units and frames follow omnitof.types: metres, radians,
seconds; θ counter-clockwise from +x; a range of +inf means no echo.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import Writer as Writer2

from omnitof.errors import InputError
from omnitof.io.carmen import repeated_top_value
from omnitof.geometry import interpolate_poses
from omnitof.io.rosbag.common import (
    _ROSBAG2_VERSION,
    BASE_FRAME,
    DEFAULT_STORAGE,
    GROUND_TRUTH_TOPIC,
    LASER_FRAME,
    LASER_SCAN,
    LASER_TYPES,
    MULTI_ECHO_SCAN,
    ODOM_FRAME,
    ODOMETRY,
    TF_MESSAGE,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    TF_TYPE_NAMES,
    TF_TYPES,
    WORLD_FRAME,
    RosbagWarning,
    _atomic_path,
    _check_written_poses,
    _connections,
    _distinct_topics,
    _frame_name,
    _header,
    _messages,
    _ns_to_s,
    _opened,
    _pick_topic,
    _PoseStream,
    _ros1_store,
    _ros2_store,
    _serialize,
    _stamp_ns,
    _storage_plugin,
    _tf_msg,
    _to_ns,
    parse_roles,
)
from omnitof.io.rosbag.odometry import (
    TopicsOption,
    edge_matrix,
    frames_without_slash,
    no_time_span,
    odometry_coverage,
    outside_odometry,
    read_bag_odometry,
    scans_span_no_time,
    spans_no_time,
    time_span,
)
from omnitof.types import (
    FLOAT32_MAX,
    MAX_BEAM_ANGLE,
    MAX_TIME_REVERSAL,
    MIN_BEAM_STEP,
    ScanSequence,
    Trajectory,
    drop_repeated_scans,
    evenly_spaced_beams,
    pad_rows,
)

__all__ = ["LaserTopics", "read_laserscan_bag", "write_laserscan_bag"]

# A laser whose plane is tilted more than this is still read, with a warning.
_MAX_LASER_TILT_RAD = math.radians(5.0)
# Scans whose first and last beams agree with the first scan's to this (rad) share its geometry;
# also the tolerance on evenly spaced beams when writing (LaserScan stores angle_min + i·increment).
_GEOMETRY_TOLERANCE = 1e-6

# --- reading -------------------------------------------------------------------------------


@dataclass(frozen=True)
class LaserTopics:
    """Where a laser-scan bag keeps what `read_laserscan_bag` reads (`--laser-topics` in the CLI).

    scan: the sensor_msgs/LaserScan or MultiEchoLaserScan topic; None: the one such topic
        ("/scan" among several).
    odometry: a nav_msgs/Odometry topic, or a tf2_msgs/TFMessage topic (such as "/tf") whose
        transform odom_frame → base_frame is the odometry; None: the one Odometry topic ("/odom"
        among several, never ground_truth), and where the bag has none, the transform on `tf`.
    ground_truth: nav_msgs/Odometry of true poses, used where present.
    tf, tf_static: the transform topics; the laser's mounting (base → laser) comes from
        tf_static, and from the first of each transform on tf where tf_static lacks it (ROS 1
        bags recorded with static_transform_publisher repeat it on /tf).
    odom_frame: the odometry's fixed frame on tf.
    base_frame: the robot's frame that the odometry moves; None: the Odometry messages'
        child_frame_id, or on tf the one frame that odom_frame moves.
    """

    scan: str | None = None
    odometry: str | None = None
    ground_truth: str = GROUND_TRUTH_TOPIC
    tf: str = TF_TOPIC
    tf_static: str = TF_STATIC_TOPIC
    odom_frame: str = ODOM_FRAME
    base_frame: str | None = None

    def __post_init__(self) -> None:
        frames_without_slash(self)
        # As in ToFTopics: the same topic for two roles would read one role's messages as the
        # other's. tf may also be tf_static (a ROS 1 bag's mounting repeated on /tf).
        roles = {"ground_truth": self.ground_truth, "tf_static": self.tf_static}
        if self.scan is not None:
            roles = {"scan": self.scan, **roles}
        if self.odometry is not None and self.odometry != self.tf:
            roles["odometry"] = self.odometry
        _distinct_topics(roles)

    @classmethod
    def parse(cls, text: str) -> LaserTopics:
        """From "ROLE=VALUE,ROLE=VALUE" (the roles are the fields), as `--laser-topics` takes
        them; ValueError naming a bad item."""
        return parse_roles(cls, text, "scan=/base_scan")


# How the errors of `read_laserscan_bag` tell a user to choose a topic or frame.
_HOW = TopicsOption("--laser-topics", "LaserTopics")


def read_laserscan_bag(path: str | Path, *, topics: LaserTopics | None = None) -> ScanSequence:
    """Read sensor_msgs/LaserScan (or MultiEchoLaserScan: each beam's first echo) and the
    robot's odometry from a ROS 1 or ROS 2 bag.

    - Topics (`LaserTopics`; default: found by type): several candidates are ambiguous unless
      one is the conventional name ("/scan", "/odom"); the ground-truth topic is never taken
      for odometry. The error lists the candidates. A topic named in `topics` (other than its
      default) that the bag lacks is an InputError listing the bag's topics.
    - Odometry: nav_msgs/Odometry messages, or where the bag has none (or `topics.odometry`
      names a tf2_msgs/TFMessage topic) the transform odom → base on /tf, as gmapping and
      slam_toolbox read it: x, y and the heading of each transform, by its own stamp (sorted;
      the last of several at one stamp).
    - Ranges: NaN, ±inf, values of 0 or less, below range_min or at range_max and beyond (each
      message its own; a reading of exactly range_max is many drivers' no-echo value) become
      +inf (no echo). Beam i is at angle_min + i·angle_increment; max_range = the largest
      finite range_max (`_max_range`: where none is finite, a repeated no-echo code or the
      farthest reading; a range_max of NaN or 0 in some messages bounds theirs by the
      others', with a RosbagWarning); intensities become `remissions` when every scan has
      one per beam. Where angle_min, angle_increment or the beam count change from scan to
      scan, the ScanSequence has per-scan geometry (`angles` (N, B), `beam_counts`).
    - Time: each scan's header stamp, in the bag's order; a stamp may be earlier than the one
      before by up to MAX_TIME_REVERSAL (1 s: stamps that jitter, kept with a RosbagWarning, as
      read_carmen keeps them), not more, and the stamps must not be all one (of more than one
      scan: stamps left unset, `scans_span_no_time`). A scan that repeats the one
      before it exactly (stamp, readings, pose) is dropped with a RosbagWarning
      (`omnitof.types.drop_repeated_scans`); one stamped alike but reading differently is kept. The odometry (its header
      stamps must not decrease either) is interpolated to each scan's stamp (linear in x, y,
      shorter arc in θ); scans outside the odometry's time span, or inside a hole in it
      (`odometry.odometry_gaps`), are dropped with a RosbagWarning; where all its poses share
      one stamp, scans at other times are an InputError instead.
    - Ground truth: Odometry messages on `topics.ground_truth`, interpolated the same way, when
      the topic has messages and covers every kept scan (else None; with a warning where it
      does not cover them).
    - sensor_pose: base → laser from the static transforms, where base is the odometry's
      child frame (default base_link) and laser the scans' frame_id, chained through
      intermediate frames and projected to the plane (x, y, yaw). An upside-down laser gets its
      angles negated. Without such a transform: zeros and a RosbagWarning.

    Raises:
        InputError: naming the bag and topic: not a bag, no or ambiguous topics, beam angles or
            odometry poses that are not finite, timestamps that go back more than 1 s or are
            all one, no scan within the odometry's span.
    """
    path = Path(path)
    topics = topics or LaserTopics()
    with _opened(path) as reader:
        scan_conns = _pick_topic(reader, path, LASER_TYPES, topics.scan, "/scan", _HOW.choose("scan"))
        found = read_bag_odometry(reader, path, odometry=topics.odometry, ground_truth=topics.ground_truth,
                                  tf=topics.tf, odom_frame=topics.odom_frame, base_frame=topics.base_frame, how=_HOW)
        odometry, odom_name = found.trajectory, found.name
        base_frame = found.base or BASE_FRAME
        odometry_rule = found.rule("scan", topics.odom_frame, topics.tf)
        first_seen = found.first_edges  # the first of each transform on topics.tf, where it was read
        tf_static_topic = topics.tf_static
        if tf_static_topic != TF_STATIC_TOPIC:  # named: it must be there
            _connections(reader, path, tf_static_topic, TF_TYPE_NAMES)
        tf_conns = [
            c for c in reader.connections if c.topic == tf_static_topic and c.msgtype in TF_TYPES
        ]
        scan_name = scan_conns[0].topic
        static = _read_static_transforms(reader, path, tf_conns)
        # ROS 1 bags recorded with static_transform_publisher repeat the mounting on /tf.
        dynamic_conns = [c for c in reader.connections if c.topic == topics.tf and c.msgtype in TF_TYPES]

        stamps: list[int] = []
        ranges: list[np.ndarray] = []
        intensities: list[np.ndarray] = []
        geometry: list[tuple[float, float, int, float]] = []  # angle_min, increment, beams, range_max
        odd_ends: list[str] = []  # scans whose angle_max disagrees with their beams (warned once)
        unread = _Unread()  # what the readings were, while none is an echo
        reversals: list[float] = []  # how far (s) each scan stamped earlier than the one before is
        unstated: list[float] = []  # stamps (s) of the scans whose range_max is NaN, 0 or less
        laser_frame = ""
        for _, msg in _messages(reader, path, scan_conns):
            ns = _stamp_ns(msg.header.stamp)
            if stamps and ns < stamps[-1]:
                # As read_carmen: a driver's stamps that jitter back a little are kept, in the
                # bag's order; a clock set back is two runs in one bag.
                back = _ns_to_s(stamps[-1] - ns)
                if back > MAX_TIME_REVERSAL:
                    raise InputError(
                        f"topic {scan_name}: timestamps go backwards: a scan stamped {_ns_to_s(ns):.9f} s follows one "
                        f"stamped {_ns_to_s(stamps[-1]):.9f} s, {back:.6f} s earlier; at most {MAX_TIME_REVERSAL:g} s is "
                        "tolerated (a clock set back: map the parts before and after it apart)",
                        path,
                    )
                reversals.append(back)
            if not stamps:
                laser_frame = _frame_name(msg.header.frame_id)
            if scan_conns[0].msgtype == MULTI_ECHO_SCAN:
                r, remission = _first_echoes(msg)
            else:
                r, remission = np.array(msg.ranges, dtype=np.float32), np.asarray(msg.intensities, dtype=np.float32)
            range_min, range_max = float(msg.range_min), float(msg.range_max)
            if not range_max > 0.0:
                # NaN, 0 or less: this message states no limit; its readings are bounded by the
                # others' (below), and the whole run is not lost to one corrupt field.
                unstated.append(_ns_to_s(ns))
                range_max = math.inf
            if not (math.isfinite(msg.angle_min) and math.isfinite(msg.angle_increment)):
                raise InputError(
                    f"topic {scan_name}: the scan at {_ns_to_s(ns):.9f} s has angle_min "
                    f"{msg.angle_min} and angle_increment {msg.angle_increment}; both must be "
                    "finite",
                    path,
                )
            _check_beams(msg, len(r), f"topic {scan_name}: the scan at {_ns_to_s(ns):.9f} s", path, odd_ends)
            with np.errstate(invalid="ignore"):
                # False for NaN; a range of 0 or less is no reading, whatever range_min says. A
                # reading of range_max itself is the no-echo value of drivers that write the
                # limit where the beam saw nothing (as read_carmen takes "at or beyond max").
                valid = (r >= range_min) & (r < range_max) & (r > 0.0)
            unread.add(r, valid, range_min, range_max)
            r[~valid] = np.inf
            stamps.append(ns)
            ranges.append(r)
            intensities.append(remission)
            geometry.append((float(msg.angle_min), float(msg.angle_increment), len(r), range_max))
        if odd_ends:
            warnings.warn(f"{path}: {len(odd_ends)} scan(s) end elsewhere than their angle_max says; their beams are "
                          f"placed by angle_min and angle_increment, as LaserScan defines them (first: {odd_ends[0]})",
                          RosbagWarning, stacklevel=2)
        if stamps and dynamic_conns and not _resolves(static, base_frame, laser_frame):
            if first_seen is None:
                first_seen = _read_static_transforms(reader, path, dynamic_conns, first_only=True)
            # Only the mounting below the robot: the odometry's own edge above it moves.
            first_seen = {child: edge for child, edge in first_seen.items()
                          if child != base_frame and edge[0] != topics.odom_frame}
            static = {**first_seen, **static}
            tf_static_topic = f"{tf_static_topic} or {topics.tf}"
    if not stamps:
        raise InputError(f"topic {scan_name}: has no message", path)
    if reversals:
        warnings.warn(
            f"{path}: {len(reversals)} scans on {scan_name} are stamped earlier than the one before (by up to "
            f"{max(reversals):.3f} s); kept in the bag's order with their own stamps",
            RosbagWarning,
            stacklevel=2,
        )
    if len(stamps) > 1 and min(stamps) == max(stamps):
        raise scans_span_no_time(f"topic {scan_name}", "scans", len(stamps), stamps[0], path)
    no_reading = unread.error(scan_name, len(stamps), path)
    if no_reading is not None:
        raise no_reading

    t = np.array([_ns_to_s(ns) for ns in stamps], dtype=np.float64)
    poses = np.zeros((len(t), 3))  # without odometry: SLAM estimates it from the scans (slam.scan_odometry)
    keep = np.ones(len(t), dtype=bool)
    if odometry is not None:
        poses = interpolate_poses(odometry, t)
        keep = ~outside_odometry(odometry, t)  # a pose across a hole in the odometry is no pose
        outside = int((~keep).sum())
        if outside and spans_no_time(odometry):
            raise no_time_span(f"the odometry (topic {odom_name})", odometry,
                               f"the scans on {scan_name} at other times ({outside} of {len(t)})", path)
        if not keep.any():
            raise InputError(f"topic {odom_name}: no scan on {scan_name} lies within {odometry_coverage(odometry)}",
                             path)
        if outside:
            warnings.warn(
                f"{path}: dropped {outside} of {len(t)} scans on {scan_name} that lie outside "
                f"{odometry_coverage(odometry)} (topic {odom_name})",
                RosbagWarning,
                stacklevel=2,
            )
    ground_truth = None
    truth = found.ground_truth
    if truth is not None:
        ground_truth = interpolate_poses(truth, t[keep])
        if np.isnan(ground_truth[:, 0]).any():
            warnings.warn(
                f"{path}: topic {topics.ground_truth} does not cover every scan "
                f"(its span is {time_span(truth)}); ground truth left out",
                RosbagWarning,
                stacklevel=2,
            )
            ground_truth = None

    kept = np.flatnonzero(keep)
    angle_min, increment, counts, range_max = (np.array(g)[kept] for g in zip(*geometry))
    angles, beam_counts = evenly_spaced_beams(
        angle_min, increment, counts, tolerance=_GEOMETRY_TOLERANCE
    )
    scan_ranges = pad_rows([ranges[i] for i in kept], np.inf, np.float32)
    remissions = None
    if all(len(intensities[i]) == len(ranges[i]) for i in kept):
        remissions = pad_rows([intensities[i] for i in kept], 0.0, np.float32)
    max_range, rule = _max_range(range_max, scan_ranges, path, scan_name)
    if unstated:
        warnings.warn(
            f"{path}: {len(unstated)} scan(s) on {scan_name} with a range_max of NaN, 0 or less (first at "
            f"{unstated[0]:.9f} s); their readings are taken up to the maximum range, {max_range:g} m",
            RosbagWarning,
            stacklevel=2,
        )
    # Readings of scans that stated no limit, and a no-echo code, are no echo from the maximum on.
    scan_ranges[scan_ranges >= np.float32(max_range)] = np.inf
    sensor_pose, flipped = _laser_pose(static, base_frame, laser_frame, path, tf_static_topic)
    if flipped:
        angles = -angles
    scans = ScanSequence(
        timestamps=t[keep],
        ranges=scan_ranges,
        angles=angles,
        odometry=poses[keep],
        sensor_pose=sensor_pose,
        max_range=max_range,
        remissions=remissions,
        ground_truth=ground_truth,
        source=str(path),
        beam_counts=beam_counts,
        max_range_rule=rule,
        odometry_rule=odometry_rule,
        odometry_known=odometry is not None,
    )
    scans = drop_repeated_scans(scans)
    if scans.repeated_scans_dropped:
        warnings.warn(
            f"{path}: {scans.repeated_scans_dropped} scans on {scan_name} repeat the scan before "
            "them exactly (stamp, readings and pose: a message recorded twice) and were dropped",
            RosbagWarning,
            stacklevel=2,
        )
    return scans


def _max_range(range_max: np.ndarray, ranges: np.ndarray, path: Path, topic: str) -> tuple[float, str]:
    """(the scans' maximum range, the rule that gave it): the largest finite range_max. Where every
    range_max is +inf (pointcloud_to_laserscan's default: the largest double, +inf as a float32)
    or unstated, a no-echo code repeated at the top of the readings (as read_carmen finds one),
    else just beyond the farthest reading."""
    finite = range_max[np.isfinite(range_max)]
    if finite.size:
        top = float(finite.max())
        spread = [f"{finite.min():g} to {top:g} m" if finite.min() < top else f"{top:g} m"]
        if finite.size < range_max.size:
            spread.append("others unbounded")
        rule = "LaserScan range_max"
        if len(spread) > 1 or finite.min() < top:
            rule += f" ({', '.join(spread)})"
        return top, rule
    readings = ranges[np.isfinite(ranges)]
    if readings.size == 0:
        raise InputError(f"topic {topic}: no reading of the scans kept is an echo: there is nothing to map", path)
    code = repeated_top_value(readings)
    if code is not None:
        value, count = code
        warnings.warn(
            f"{path}: topic {topic} states no finite range_max; {count} readings of exactly {value:g} m, the "
            "largest, are taken for the laser's no-echo value",
            RosbagWarning,
            stacklevel=3,
        )
        return value, f"repeated top value {value:g} m ({count} readings; range_max not finite)"
    # The farthest reading is an echo: the maximum lies just beyond it.
    farthest = np.float32(readings.max())
    return float(np.nextafter(farthest, np.float32(np.inf))), f"the farthest reading, {float(farthest):g} m (range_max not finite)"


class _Unread:
    """What a bag's readings were while none of them is an echo: how many say no reading (NaN,
    0 m or less, below range_min) and how many that the beam saw nothing within range_max. A bag
    without an echo whose readings say no reading is refused naming them (`error`): the later
    no-echo message would call them beams that saw nothing."""

    def __init__(self) -> None:
        self.echoed = False  # once a reading is an echo, nothing more is counted
        self.unread = 0
        self.nothing = 0
        self.kinds: set[str] = set()
        self.range_min: list[float] = []  # of the scans with readings below it
        self.range_max: float | None = None  # of a scan whose range_min lies above it: none can be valid

    def add(self, r: np.ndarray, valid: np.ndarray, range_min: float, range_max: float) -> None:
        if self.echoed or valid.any():
            self.echoed = True
            return
        with np.errstate(invalid="ignore"):
            nothing = r >= range_max  # +inf too
            below = (r > 0.0) & (r < range_min) & ~nothing
        self.nothing += int(nothing.sum())
        self.unread += len(r) - int(nothing.sum())
        self.kinds |= {kind for kind, seen in (("NaN", np.isnan(r).any()),
                                               ("0 m or less", (r <= 0.0).any())) if seen}
        if below.any():
            self.range_min.append(range_min)
            if range_min > range_max:
                self.range_max = range_max

    def error(self, topic: str, scans: int, path: Path) -> InputError | None:
        if self.echoed or not self.unread:
            return None
        kinds = [kind for kind in ("NaN", "0 m or less") if kind in self.kinds]
        if self.range_min:
            lo, hi = min(self.range_min), max(self.range_min)
            below = f"the scans' range_min {lo:g} m" if lo == hi else f"their range_min ({lo:g} to {hi:g} m)"
            above = "" if self.range_max is None else f" (above their range_max {self.range_max:g} m)"
            kinds.append(f"below {below}{above}")
        what = f"{', or '.join(kinds)}, which LaserScan takes for no reading"
        total = self.unread + self.nothing
        if not self.nothing:
            return InputError(f"topic {topic}: every one of the {total} readings of the {scans} scans is {what}: "
                              "there is nothing to map", path)
        return InputError(f"topic {topic}: no reading of the {scans} scans is an echo: {self.unread} of the {total} "
                          f"are {what}, and the other {self.nothing} saw nothing within range_max: there is nothing "
                          "to map", path)


def _check_beams(msg: Any, beams: int, where: str, path: Path, odd_ends: list[str]) -> None:
    """InputError where the beams' angles are no laser's: all at one bearing, or beyond ±2π (as
    the CARMEN reader refuses them); `where` is appended to `odd_ends` where angle_max is more
    than an increment off the last beam, which omnitof places at angle_min + (beams - 1)·increment
    as LaserScan defines it (the caller warns once)."""
    start, step = float(msg.angle_min), float(msg.angle_increment)
    if beams > 1 and abs(step) < MIN_BEAM_STEP:
        raise InputError(f"{where} has angle_increment {step:g}: it would put all {beams} beams at one bearing", path)
    last = start + (beams - 1) * step
    if not (abs(start) <= MAX_BEAM_ANGLE and abs(last) <= MAX_BEAM_ANGLE):
        raise InputError(f"{where} has angle_min {start:g} and angle_increment {step:g}, which put its {beams} beams at "
                         f"{start:.6g} .. {last:.6g} rad; a laser's beams lie within ±2π", path)
    if beams > 1 and not abs(float(msg.angle_max) - last) <= 1.5 * abs(step):  # False for NaN too
        odd_ends.append(f"{where} has {beams} beams from {start:.6g} rad every {step:.6g} rad, the last at "
                        f"{last:.6g} rad, but angle_max {float(msg.angle_max):.6g} rad")


def _first_echoes(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """(ranges, intensities) of a sensor_msgs/MultiEchoLaserScan: each beam's first echo, as
    Cartographer reads them (+inf for a beam without one; intensities only where every beam has
    one for its first echo, else none)."""
    # rosbags gives each beam's echoes as a message of its own: one pass over the beams.
    ranges = np.array([e.echoes[0] if len(e.echoes) else np.inf for e in msg.ranges], dtype=np.float32)
    if len(msg.intensities) == len(msg.ranges) and all(len(e.echoes) for e in msg.intensities):
        return ranges, np.array([e.echoes[0] for e in msg.intensities], dtype=np.float32)
    return ranges, np.zeros(0, dtype=np.float32)


def _read_static_transforms(
    reader: AnyReader, path: Path, connections: Sequence[Any], *, first_only: bool = False
) -> dict[str, tuple[str, np.ndarray]]:
    """child frame → (parent frame, parent_T_child 4×4) from tf2_msgs/TFMessage messages: the
    last of each edge, or with `first_only` the first."""
    edges: dict[str, tuple[str, np.ndarray]] = {}
    for _, msg in _messages(reader, path, connections):
        for tf in msg.transforms:
            child = _frame_name(tf.child_frame_id)
            if first_only and child in edges:
                continue
            edges[child] = (_frame_name(tf.header.frame_id), edge_matrix(tf))
    return edges


def _root(edges: dict[str, tuple[str, np.ndarray]], frame: str) -> tuple[str, np.ndarray]:
    """(the root of `frame`'s chain of edges, root_T_frame 4×4)."""
    matrix, seen = np.eye(4), {frame}
    while frame in edges:
        parent, parent_T_child = edges[frame]
        if parent in seen:
            break  # a cycle: tf is a tree, so give up on it
        matrix, frame = parent_T_child @ matrix, parent
        seen.add(frame)
    return frame, matrix


def _resolves(edges: dict[str, tuple[str, np.ndarray]], base: str, laser: str) -> bool:
    """Whether `edges` join the laser's frame to the base's (or there is nothing to join)."""
    return not laser or laser == base or _root(edges, laser)[0] == _root(edges, base)[0]


def _laser_pose(
    edges: dict[str, tuple[str, np.ndarray]], base: str, laser: str, path: Path, topic: str
) -> tuple[np.ndarray, bool]:
    """(robot_T_sensor (x, y, yaw), upside down?) from static transforms; zeros if unknown."""
    if not laser or laser == base:
        return np.zeros(3), False
    root_laser, root_T_laser = _root(edges, laser)
    root_base, root_T_base = _root(edges, base)
    if root_laser != root_base:
        warnings.warn(
            f"{path}: no static transform {base} → {laser} on {topic}; the laser is assumed "
            "at the robot's origin, facing forward (sensor_pose = 0)",
            RosbagWarning,
            stacklevel=3,
        )
        return np.zeros(3), False
    with np.errstate(all="ignore"):
        base_T_laser = np.linalg.inv(root_T_base) @ root_T_laser
    if not np.isfinite(base_T_laser).all():
        raise InputError(f"the static transform {base} → {laser} on {topic} is not finite", path)
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


# --- writing -------------------------------------------------------------------------------


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
    odometry_on_tf: bool = False,
    tf_topic: str = "/tf",
    overwrite: bool = False,
) -> None:
    """Write a ScanSequence as a ROS 1 (version=1) or ROS 2 (version=2) bag.

    Per scan, in time order: the odometry pose (nav_msgs/Odometry odom → base_link), the ground
    truth when the sequence has it (world → base_link), and the scan (sensor_msgs/LaserScan in
    frame "laser", range_min 0, range_max = max_range, +inf kept for no echo and written for
    NaN and readings of 0 m or less, intensities from remissions), all with the scan's stamp. One static transform base_link → laser from
    sensor_pose on /tf_static (latched in ROS 1). Readings beyond max_range stay in the bag as
    they are; readers (this one too) take them for no echo. With `odometry_on_tf` the odometry
    is the transform odom → base_link on `tf_topic` (tf2_msgs/TFMessage) instead of Odometry
    messages, as robots that publish it only to tf record it. Scans without odometry
    (`odometry_known` False) are written without it, and read back so.

    Args:
        path: a ".bag" file for version 1 (ROS 1 readers recognise bags by it); a folder not
            ending in ".bag" for version 2.
        scans: evenly spaced beams in each scan (LaserScan stores angle_min +
            i·angle_increment, in float32; per-scan geometry gives each message its own),
            timestamps >= 0 and not decreasing by more than MAX_TIME_REVERSAL (1 s): a scan
            stamped earlier than one before it keeps its stamp and its place in the bag (its
            odometry message goes where its stamp puts it among the others).
        storage: ROS 2 storage, "mcap" or "sqlite3".
        overwrite: replace an existing bag at `path`.

    Raises:
        BagExistsError: `path` exists and overwrite is False.
        ValueError: uneven beams, timestamps going back more than 1 s or all one (of more than one
            scan), odometry or ground truth that is not finite, one topic for two roles, a bad
            path or version.
    """
    path = Path(path)
    roles = {"scan_topic": scan_topic, "tf_static_topic": tf_static_topic}
    if scans.odometry_known:
        roles["tf_topic" if odometry_on_tf else "odom_topic"] = tf_topic if odometry_on_tf else odom_topic
    if scans.ground_truth is not None:  # written only then
        roles["ground_truth_topic"] = ground_truth_topic
    _distinct_topics(roles)
    if version not in (1, 2):
        raise ValueError(f"version must be 1 (ROS 1) or 2 (ROS 2), got {version!r}")
    if version == 1 and path.suffix != ".bag":
        raise ValueError(f"{path}: a ROS 1 bag must end in '.bag' (readers recognise it so)")
    if version == 2 and path.suffix == ".bag":
        raise ValueError(
            f"{path}: a ROS 2 bag folder must not end in '.bag' (readers take that for ROS 1)"
        )
    plugin = _storage_plugin(storage)
    if scans.per_scan_geometry:
        geometry = [_even_beams(scans.scan_angles(k)) for k in range(len(scans))]
    else:
        geometry = [_even_beams(scans.angles)] * len(scans)
    stamps = [_to_ns(t) for t in scans.timestamps]
    # A stamp a little earlier than one before it (a CARMEN log's jitter: Intel's go back 631
    # times, by up to 0.9 s) is written as it is, in the sequence's order, as the reader keeps
    # it; the bag's own message times never go back, so that readers keep that order.
    stamp_ns = np.asarray(stamps, dtype=np.int64)
    written_at = np.maximum.accumulate(stamp_ns) if len(stamp_ns) else stamp_ns
    back = (written_at - stamp_ns) / 1e9
    if len(back) and back.max() > MAX_TIME_REVERSAL:
        k = int(np.argmax(back))
        raise ValueError(f"write_laserscan_bag: scan {k} is stamped {back[k]:.6f} s earlier than one before it; "
                         f"at most {MAX_TIME_REVERSAL:g} s is written (read_laserscan_bag refuses more)")
    # The odometry's stamps must not go back (the reader refuses that): its messages are the
    # scans' poses sorted by stamp, so that the reader, interpolating it to each scan's stamp,
    # finds that scan's own pose there.
    by_time = np.argsort(scans.timestamps, kind="stable")
    if len(stamp_ns) > 1 and stamp_ns.min() == stamp_ns.max():  # not first against last: stamps may go back
        raise ValueError(f"write_laserscan_bag: all {len(stamps)} scans are stamped {scans.timestamps[0]!r} s; "
                         "read_laserscan_bag refuses scans that span no time (stamps left unset)")
    if not len(scans):
        raise ValueError("write_laserscan_bag needs at least one scan")
    if not (math.isfinite(scans.max_range) and 0.0 < scans.max_range <= FLOAT32_MAX
            and np.float32(scans.max_range) > 0.0):
        # LaserScan's range_max is a float32: 1e300 overflows it, 1e-320 is 0 in it.
        raise ValueError(f"max_range must be a positive float32 number, got {scans.max_range}")
    for name, poses in (("odometry", scans.odometry), ("ground_truth", scans.ground_truth)):
        if poses is not None:
            _check_written_poses(poses, f"the scans' {name}")
    _check_written_poses(scans.sensor_pose[None, :], "the sensor")
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
            streams = []
            if scans.odometry_known:
                conn_odom = add(tf_topic, TF_MESSAGE) if odometry_on_tf else add(odom_topic, ODOMETRY)
                streams.append(
                    _PoseStream(
                        writer, conn_odom, store,
                        Trajectory(scans.timestamps[by_time], scans.odometry[by_time]),
                        ODOM_FRAME, BASE_FRAME, ros1=ros1, as_tf=odometry_on_tf,
                    )
                )  # fmt: skip
            if scans.ground_truth is not None:
                conn_truth = add(ground_truth_topic, ODOMETRY)
                streams.append(
                    _PoseStream(
                        writer, conn_truth, store,
                        Trajectory(scans.timestamps[by_time], scans.ground_truth[by_time]),
                        WORLD_FRAME, BASE_FRAME, ros1=ros1,
                    )
                )  # fmt: skip
            tf = _tf_msg(store, stamps[0], scans.sensor_pose, BASE_FRAME, LASER_FRAME, ros1=ros1)
            writer.write(conn_tf, stamps[0], _serialize(store, tf, TF_MESSAGE, ros1))
            scan_cls = store.types[LASER_SCAN]
            for k, (ns, at) in enumerate(zip(stamps, written_at.tolist())):
                for stream in streams:
                    stream.write_until(at)
                angle_min, increment = geometry[k]
                ranges = scans.scan_ranges(k)
                with np.errstate(invalid="ignore"):  # no reading to the reader: no echo, as ScanSequence has it
                    ranges = np.where(ranges > 0.0, ranges, np.inf)
                msg = scan_cls(
                    header=_header(store, ns, LASER_FRAME, ros1=ros1),
                    angle_min=angle_min,
                    angle_max=angle_min + increment * (len(ranges) - 1),
                    angle_increment=increment,
                    time_increment=0.0,
                    scan_time=0.0,
                    range_min=0.0,
                    range_max=float(scans.max_range),
                    ranges=np.ascontiguousarray(ranges, dtype=np.float32),
                    intensities=np.ascontiguousarray(intensities[k, : len(ranges)], dtype=np.float32),
                )
                writer.write(conn_scan, at, _serialize(store, msg, LASER_SCAN, ros1))


def _adder(writer: Any, store: Any, ros1: bool) -> Any:
    def add(topic: str, msgtype: str, *, latching: bool = False) -> Any:
        if ros1:
            return writer.add_connection(
                topic, msgtype, typestore=store, latching=1 if latching else None
            )
        return writer.add_connection(topic, msgtype, typestore=store)

    return add


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
