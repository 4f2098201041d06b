"""Every reader against mutated valid files (property-based, hypothesis): truncation, byte
flips, deleted and repeated lines, numbers replaced by words, NaN, infinity or huge values,
other encodings, inserted bytes. Each must give a valid result or raise omnitof's own error
(OmnitofError, which the command prints as one line), never another exception.

The valid files are made by the project's own writers. The search is derandomised and
bounded (FUZZ below), so the module takes well under a minute on two cores and every CI run
tries the same inputs; OMNITOF_FUZZ_SCALE=10 searches ten times harder."""

from __future__ import annotations

import math
import os
import re
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from omnitof.errors import OmnitofError
from omnitof.types import ScanSequence

# OMNITOF_FUZZ_SCALE=10 searches ten times harder (locally; CI keeps the bounded budget).
SCALE = float(os.environ.get("OMNITOF_FUZZ_SCALE", "1"))
pytestmark = pytest.mark.filterwarnings("ignore::omnitof.errors.OmnitofWarning")  # warnings are fine

FUZZ = settings(max_examples=int(200 * SCALE), deadline=None, derandomize=True, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
SLOW_FUZZ = settings(FUZZ, max_examples=int(60 * SCALE))  # tens of milliseconds an example

# Words, non-numbers and extremes that replace a token of a valid file.
TOKENS = [b"nan", b"NaN", b"inf", b"-inf", b"1e308", b"-1e308", b"1e999", b"1e-320", b"0", b"-0", b"-1",
          b"4294967296", b"9" * 40, b"x", b"", b"[]", b"{}", b"null", b"true", b"~", b"0x1f", b"1_000",
          "１２".encode(), b"'0'", b"- a", b": b"]
_TOKEN = re.compile(rb"[^\s:,\[\]{}]+")


# --- mutations --------------------------------------------------------------------------------


def mutate(data: bytes, draw: Callable) -> bytes:
    """One to three random mutations of `data` (see the module notes)."""
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["truncate", "flip", "delete_line", "repeat_line", "token", "token",
                                     "encoding", "insert"]))
        data = MUTATIONS[kind](data, draw)
    return data


def _truncate(data: bytes, draw: Callable) -> bytes:
    return data[: draw(st.integers(0, max(len(data) - 1, 0)))]


def _flip(data: bytes, draw: Callable) -> bytes:
    if not data:
        return data
    i = draw(st.integers(0, len(data) - 1))
    return data[:i] + bytes([data[i] ^ draw(st.integers(1, 255))]) + data[i + 1:]


def _lines(data: bytes, draw: Callable, repeat: bool) -> bytes:
    lines = data.splitlines(keepends=True)
    if not lines:
        return data
    i = draw(st.integers(0, len(lines) - 1))
    lines[i:i + 1] = [lines[i], lines[i]] if repeat else []
    return b"".join(lines)


def _token(data: bytes, draw: Callable) -> bytes:
    spans = [m.span() for m in _TOKEN.finditer(data)]
    if not spans:
        return data
    a, b = spans[draw(st.integers(0, len(spans) - 1))]
    return data[:a] + draw(st.sampled_from(TOKENS)) + data[b:]


def _encoding(data: bytes, draw: Callable) -> bytes:
    how = draw(st.sampled_from(["utf-16", "latin-1", "bad utf-8", "bom"]))
    if how == "utf-16":
        return data.decode("utf-8", errors="replace").encode("utf-16")
    if how == "latin-1":
        return data.replace(b"e", "é".encode("latin-1"), 3)
    if how == "bad utf-8":
        i = draw(st.integers(0, len(data)))
        return data[:i] + b"\xff\xfe\xc3" + data[i:]
    return b"\xef\xbb\xbf" + data


def _insert(data: bytes, draw: Callable) -> bytes:
    i = draw(st.integers(0, len(data)))
    return data[:i] + draw(st.binary(min_size=1, max_size=16)) + data[i:]


MUTATIONS = {"truncate": _truncate, "flip": _flip, "token": _token, "encoding": _encoding, "insert": _insert,
             "delete_line": lambda d, draw: _lines(d, draw, False),
             "repeat_line": lambda d, draw: _lines(d, draw, True)}


def read_or_refuse(read: Callable, *args, **kwargs):
    """The reader's result, or None when it refused with omnitof's own error; any other
    exception fails the test (hypothesis then shrinks the input and shows it)."""
    try:
        return read(*args, **kwargs)
    except OmnitofError as err:
        assert str(err), "an error must say what is wrong"
        return None


_SCRATCH: list[Path] = []  # this module's scratch root, under pytest's own temporary folder


@pytest.fixture(scope="module", autouse=True)
def _scratch_root(tmp_path_factory):
    """Every example's files live under one folder that pytest removes with its old runs, so an
    example that fails before its cleanup leaves nothing in the system's temporary folder."""
    _SCRATCH.append(tmp_path_factory.mktemp("fuzz"))
    yield
    shutil.rmtree(_SCRATCH.pop(), ignore_errors=True)


def scratch() -> Path:
    return Path(tempfile.mkdtemp(prefix="example-", dir=_SCRATCH[-1]))


def check_scans(scans: ScanSequence) -> None:
    """What every reader promises of a ScanSequence (omnitof.types, docs/conventions.md)."""
    assert len(scans) >= 1
    assert np.isfinite(scans.timestamps).all() and np.isfinite(scans.odometry).all()
    assert np.isfinite(scans.sensor_pose).all()
    assert math.isfinite(scans.max_range) and scans.max_range > 0
    beams = scans.ranges[scans.beam_mask]
    assert not np.isnan(beams).any() and (beams > 0).all()  # a reading, or +inf: no echo
    for i in (0, len(scans) - 1):
        assert np.isfinite(scans.scan_angles(i)).all()


# --- the valid files --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def seeds(tmp_path_factory, corridor_loop) -> dict[str, Path]:
    """One valid file (or bag) per reader, made by omnitof's writers."""
    from omnitof.calibration import Calibration, save_calibration
    from omnitof.calibration.masks import write_polygon_file
    from omnitof.io.carmen import write_carmen
    from omnitof.io.ply import write_ply
    from omnitof.io.rosbag import write_laserscan_bag
    from omnitof.io.rosmap import write_ros_map
    from omnitof.io.tum import write_tum
    from omnitof.sensor.design import default_rig
    from omnitof.slam.config import load_config
    from omnitof.types import OccupancyMap, Trajectory

    folder = tmp_path_factory.mktemp("seeds")
    scans = corridor_loop.slice(0, 4)
    few = ScanSequence(scans.timestamps, scans.ranges[:, ::30], scans.angles[::30], scans.odometry,
                       max_range=scans.max_range, ground_truth=scans.ground_truth)
    paths = {"carmen": folder / "new.log", "tum": folder / "t.tum", "relations": folder / "r.relations",
             "config": folder / "c.yaml", "calibration": folder / "cal.yaml", "polygons": folder / "p.yaml",
             "rosmap": folder / "map.yaml", "ply": folder / "v.ply", "ros1": folder / "scans.bag",
             "ros2": folder / "scans", "ros2_sqlite": folder / "scans_db"}
    write_carmen(paths["carmen"], few)
    (folder / "old.log").write_text(
        "PARAM robot_front_laser_max 7.5\nPARAM laser_front_laser_fov 180 nohost 0\n"
        "ODOM 0.0 0.0 0.0 0.1 0 0 1.0 host 0.0\n"
        "FLASER 4 1.0 2.0 3.0 8.0 0.1 0.0 0.0 0.0 0.0 0.0 1.0 host 0.0\n"
        "FLASER 4 1.1 2.1 3.1 8.0 0.2 0.0 0.0 0.1 0.0 0.0 1.1 host 0.1\n"
        "RAWLASER1 0 -1.57 3.14 1.57 30.0 0.01 0 3 1.0 2.0 3.0 0 1.05 host 0.05\n"
    )
    write_tum(paths["tum"], Trajectory(scans.timestamps, scans.odometry))
    paths["relations"].write_text("".join(
        f"{scans.timestamps[i]:.6f} {scans.timestamps[i + 1]:.6f} 0.1 0.0 0.000000 0.000000 0.000000 0.01\n"
        for i in range(3)))
    paths["config"].write_text(load_config(preset="laser180-scanmatch").to_yaml())
    save_calibration(Calibration.from_rig(default_rig()), paths["calibration"])
    write_polygon_file(paths["polygons"], {"front": np.array([[1.0, 2.0], [30.0, 2.0], [15.0, 40.0]]),
                                           "left": np.array([[50.0, 60.0], [80.0, 60.0], [70.0, 90.0]])})
    grid = np.array([[2.0, -2.0, 0.0], [0.0, 2.0, -2.0]], np.float32)
    write_ros_map(paths["rosmap"], OccupancyMap(grid, grid != 0, 0.05, (1.0, -2.0)))
    write_ply(paths["ply"], np.array([[0.0, 0.1, 0.2], [1.0, 1.5, 2.0]]), np.array([[255, 0, 0], [0, 255, 0]], np.uint8))
    write_laserscan_bag(paths["ros1"], few, version=1)
    write_laserscan_bag(paths["ros2"], few, version=2)
    write_laserscan_bag(paths["ros2_sqlite"], few, version=2, storage="sqlite3")
    _write_tof_bag(folder / "tof")
    paths["tof"] = folder / "tof"
    paths["carmen_old"] = folder / "old.log"
    # Held odometry (each FLASER carries the last ODOM pose, 0.07 s old) over 30 scans: the
    # reader's interpolation of ODOM to the scans' stamps runs on it.
    held = []
    for k in range(31):
        t = 5.0 + 0.1 * k
        pose = f"{0.5 * t:.6f} 0.000000 {0.6 * t - 3.0:.6f}"
        held.append(f"ODOM {pose} 0.5 0.6 0 {t:.6f} host {t:.6f}")
        held.append(f"FLASER 4 1.0 2.0 3.0 4.0 {pose} {pose} {t + 0.07:.6f} host {t + 0.07:.6f}")
    paths["carmen_held"] = folder / "held.log"
    paths["carmen_held"].write_text("\n".join(held) + "\n")
    paths["world"] = Path(__file__).resolve().parents[1] / "python" / "omnitof" / "worlds" / "room.yaml"
    return paths


def _write_tof_bag(path: Path) -> None:
    """Three frames of an 8 × 6 camera with odometry, ground truth and a sidecar (its rig)."""
    from omnitof.io.rosbag.tof import ToFFrameStamped, write_tof_bag
    from omnitof.sensor.camera import Camera
    from omnitof.types import Trajectory

    camera = Camera(8, 6, 10.0, 11.0, 3.5, 2.5, (-0.1, 0.01, 0.001, -0.002, 0.0003))
    frames = [ToFFrameStamped(1.0 + 0.1 * k, np.full((6, 8), 2.0 + k, np.float32), np.full((6, 8), 50.0, np.float32))
              for k in range(3)]
    poses = Trajectory([1.0, 1.1, 1.2], [[0.0, 0.0, 0.0], [0.1, 0.0, 0.01], [0.2, 0.0, 0.02]])
    write_tof_bag(path, frames, camera=camera, odometry=poses, ground_truth=poses,
                  sidecar={"world": "room", "note": [1.0, 2.0]})


def mutated_copy(seed: Path, draw: Callable, name: str | None = None) -> Path:
    path = scratch() / (name or seed.name)
    path.write_bytes(mutate(seed.read_bytes(), draw))
    return path


# --- the readers ------------------------------------------------------------------------------


@FUZZ
@given(data=st.data())
def test_carmen_logs(seeds, data):
    from omnitof.io.carmen import read_carmen

    seed = seeds[data.draw(st.sampled_from(["carmen", "carmen_old", "carmen_held"]))]
    path = mutated_copy(seed, data.draw)
    log = read_or_refuse(read_carmen, path, skip_bad_lines=data.draw(st.booleans()))
    if log is not None:
        check_scans(log.scans)
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_tum_trajectories(seeds, data):
    from omnitof.io.tum import read_tum

    path = mutated_copy(seeds["tum"], data.draw)
    traj = read_or_refuse(read_tum, path)
    if traj is not None:
        assert len(traj) >= 1 and np.all(np.diff(traj.timestamps) > 0)
        assert np.isfinite(traj.timestamps).all() and np.isfinite(traj.poses).all()
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_benchmark_relations(seeds, data):
    from omnitof.eval.relations import read_relations

    path = mutated_copy(seeds["relations"], data.draw)
    rel = read_or_refuse(read_relations, path)
    if rel is not None:
        assert len(rel) >= 1 and np.isfinite(rel.t1).all() and np.isfinite(rel.t2).all()
        assert np.isfinite(rel.delta).all()
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_configurations(seeds, data):
    from omnitof.slam.config import SlamConfig, load_config

    path = mutated_copy(seeds["config"], data.draw)
    cfg = read_or_refuse(load_config, path)
    if cfg is not None:
        assert isinstance(cfg, SlamConfig)
        assert SlamConfig.model_validate(cfg.model_dump()) == cfg  # every value within its domain
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_worlds(seeds, data):
    from omnitof.sim.worlds import load_world

    path = mutated_copy(seeds["world"], data.draw)
    world = read_or_refuse(load_world, path)
    if world is not None:
        walls = world.segments_at(0.6)
        assert np.isfinite(np.asarray(walls, dtype=float)).all()
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_calibrations(seeds, data):
    from omnitof.calibration import load_calibration

    path = mutated_copy(seeds["calibration"], data.draw)
    cal = read_or_refuse(load_calibration, path)
    if cal is not None:
        assert np.isfinite(cal.camera.K).all() and len(cal.planes) >= 1
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_polygon_files(seeds, data):
    from omnitof.calibration.masks import read_polygon_file

    path = mutated_copy(seeds["polygons"], data.draw)
    polygons = read_or_refuse(read_polygon_file, path)
    if polygons is not None:
        for points in polygons.values():
            assert points.ndim == 2 and points.shape[1] == 2 and np.isfinite(points).all()
    shutil.rmtree(path.parent)


@FUZZ
@given(data=st.data())
def test_ros_maps(seeds, data):
    from omnitof.io.rosmap import read_ros_map

    folder = scratch()
    for part in ("map.yaml", "map.pgm"):
        shutil.copy(seeds["rosmap"].parent / part, folder / part)
    target = folder / data.draw(st.sampled_from(["map.yaml", "map.pgm"]))
    target.write_bytes(mutate(target.read_bytes(), data.draw))
    occ = read_or_refuse(read_ros_map, folder / "map.yaml")
    if occ is not None:
        assert occ.log_odds.shape == occ.known.shape and occ.resolution > 0 and math.isfinite(occ.resolution)
        assert np.isfinite(occ.origin).all()
    shutil.rmtree(folder)


@FUZZ
@given(data=st.data())
def test_ply_point_clouds(seeds, data):
    from omnitof.io.ply import read_ply

    path = mutated_copy(seeds["ply"], data.draw)
    cloud = read_or_refuse(read_ply, path)
    if cloud is not None:
        points, colours = cloud
        assert points.ndim == 2 and points.shape[1] == 3
        assert colours is None or len(colours) == len(points)
    shutil.rmtree(path.parent)


def _bag_copy(seed: Path) -> tuple[Path, list[Path]]:
    """A copy of a bag (file or folder) and the files in it that mutations may hit."""
    folder = scratch()
    if seed.is_dir():
        shutil.copytree(seed, folder / seed.name)
        copy = folder / seed.name
        return copy, sorted(p for p in copy.iterdir() if p.is_file())
    shutil.copy(seed, folder / seed.name)
    return folder / seed.name, [folder / seed.name]


@SLOW_FUZZ
@given(data=st.data())
def test_laserscan_bags(seeds, data):
    from omnitof.io.rosbag import read_laserscan_bag

    bag, files = _bag_copy(seeds[data.draw(st.sampled_from(["ros1", "ros2", "ros2_sqlite"]))])
    target = data.draw(st.sampled_from(files))
    target.write_bytes(mutate(target.read_bytes(), data.draw))
    scans = read_or_refuse(read_laserscan_bag, bag)
    if scans is not None:
        check_scans(scans)
    shutil.rmtree(bag.parent)


@SLOW_FUZZ
@given(data=st.data())
def test_tof_bags(seeds, data):
    from omnitof.io.rosbag.tof import read_tof_bag

    bag, files = _bag_copy(seeds["tof"])
    target = data.draw(st.sampled_from(files))
    target.write_bytes(mutate(target.read_bytes(), data.draw))

    def read_all(path):
        opened = read_tof_bag(path)
        return opened, list(opened.frames())

    read = read_or_refuse(read_all, bag)
    if read is not None:
        opened, frames = read
        assert len(frames) <= opened.n_frames and opened.camera.shape == (6, 8)
        for frame in frames:
            assert frame.distance.shape == frame.amplitude.shape == opened.camera.shape
    shutil.rmtree(bag.parent)


@SLOW_FUZZ
@given(data=st.data())
def test_laserscan_bags_with_hostile_values(data):
    # Well-formed messages with hostile numbers: NaN, infinity and huge poses, stamps, ranges
    # and beam geometry (a byte flip rarely makes such a message).
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    from omnitof.io.rosbag import read_laserscan_bag

    store = get_typestore(Stores.ROS2_HUMBLE)
    t = store.types
    odd = st.sampled_from([0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 1e308, -1e308, 1e-300, 3.0])
    value = st.one_of(odd, st.floats(-1e3, 1e3))  # float64 fields
    odd32 = st.sampled_from([0.0, 1.0, -1.0, math.nan, math.inf, -math.inf, 3e38, -3e38, 1e-38, 0.5])
    value32 = st.one_of(odd32, st.floats(-1e3, 1e3, width=32))  # float32 fields

    def header(ns, frame):
        stamp = t["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        return t["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def odom(ns):
        vec = t["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
        q = [data.draw(value) for _ in range(4)]
        pose = t["geometry_msgs/msg/Pose"](
            position=t["geometry_msgs/msg/Point"](x=data.draw(value), y=data.draw(value), z=0.0),
            orientation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
        return t["nav_msgs/msg/Odometry"](
            header=header(ns, "odom"), child_frame_id="base_link",
            pose=t["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
            twist=t["geometry_msgs/msg/TwistWithCovariance"](
                twist=t["geometry_msgs/msg/Twist"](linear=vec, angular=vec), covariance=np.zeros(36)))

    def scan(ns):
        n = data.draw(st.integers(0, 6))
        return t["sensor_msgs/msg/LaserScan"](
            header=header(ns, "laser"), angle_min=data.draw(value32), angle_max=0.0,
            angle_increment=data.draw(value32), time_increment=0.0, scan_time=0.0,
            range_min=data.draw(value32), range_max=data.draw(value32),
            ranges=np.array([data.draw(value32) for _ in range(n)], np.float32),
            intensities=np.zeros(data.draw(st.sampled_from([0, n])), np.float32))

    def tf():
        q = [data.draw(value) for _ in range(4)]
        transform = t["geometry_msgs/msg/TransformStamped"](
            header=header(0, "base_link"), child_frame_id="laser",
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](x=data.draw(value), y=data.draw(value), z=0.0),
                rotation=t["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3])))
        return t["tf2_msgs/msg/TFMessage"](transforms=[transform])

    stamps = sorted(data.draw(st.lists(st.integers(0, 2**40), min_size=1, max_size=4)))
    folder = scratch()
    with Writer(folder / "bag", version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        if data.draw(st.booleans()):
            c_tf = writer.add_connection("/tf_static", "tf2_msgs/msg/TFMessage", typestore=store)
            writer.write(c_tf, 0, store.serialize_cdr(tf(), "tf2_msgs/msg/TFMessage"))
        c_odom = writer.add_connection("/odom", "nav_msgs/msg/Odometry", typestore=store)
        c_scan = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", typestore=store)
        for k, ns in enumerate(stamps):
            writer.write(c_odom, 2 * k + 1, store.serialize_cdr(odom(ns), "nav_msgs/msg/Odometry"))
            writer.write(c_scan, 2 * k + 2, store.serialize_cdr(scan(ns), "sensor_msgs/msg/LaserScan"))
    scans = read_or_refuse(read_laserscan_bag, folder / "bag")
    if scans is not None:
        check_scans(scans)
    shutil.rmtree(folder)


@SLOW_FUZZ
@given(data=st.data())
def test_the_slam_command_on_mutated_logs(seeds, data):
    # End to end: whatever a reader accepts, the run completes (exit 0, a complete folder) or
    # stops with one line (exit 2, no folder); no traceback, no half-written folder.
    from omnitof.cli import main
    from omnitof.results import RESULT_FILES

    path = mutated_copy(seeds[data.draw(st.sampled_from(["carmen", "carmen_old"]))], data.draw)
    out = path.parent / "run"
    code = main(["slam", str(path), "--out", str(out), "--preset", "sim2d", "--particles", "2", "--quiet",
                 "--skip-bad-lines"])
    if code == 0:
        names = {p.name for p in out.iterdir()}
        assert {"map.pgm", "map.yaml", "trajectory.tum", "summary.yaml"} <= names <= RESULT_FILES
    else:
        assert code == 2 and not out.exists()
    assert sorted(p.name for p in path.parent.iterdir()) == sorted([path.name] + (["run"] if code == 0 else []))
    shutil.rmtree(path.parent)
