"""Every writer against hostile values (property-based, hypothesis): whatever a writer accepts,
the project's own reader reads back as written; whatever the reader would refuse, the writer
refuses first with a ValueError (or omnitof's own error) and leaves no file behind.

tests/test_fuzz.py mutates the files; this module mutates what is written: NaN, infinities,
subnormal, huge and negative values dropped into valid trajectories, scans, maps and clouds,
and file names and comments with YAML's and PLY's special characters. The search is
derandomised and bounded, like test_fuzz.py's."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from omnitof.errors import OmnitofError
from omnitof.types import OccupancyMap, ScanSequence, Trajectory

SCALE = float(os.environ.get("OMNITOF_FUZZ_SCALE", "1"))
pytestmark = pytest.mark.filterwarnings("ignore::omnitof.errors.OmnitofWarning")
PROPERTY = settings(max_examples=int(150 * SCALE), deadline=None, derandomize=True, database=None,
                    suppress_health_check=[HealthCheck.too_slow])

HOSTILE = st.sampled_from([math.nan, math.inf, -math.inf, 1e300, -1e300, 1e10, -1e10, 1e-320, -0.0, 0.0, -1.0])


def poisoned(draw, array: np.ndarray) -> np.ndarray:
    """`array` with up to two entries replaced by hostile values."""
    out = np.array(array, dtype=np.float64)
    for _ in range(draw(st.integers(0, 2))):
        out.flat[draw(st.integers(0, out.size - 1))] = draw(HOSTILE)
    return out


def written_or_refused(write, path: Path, *args, **kwargs) -> bool:
    """Whether the writer wrote `path`; a refusal must be a ValueError or omnitof's own error,
    must say what is wrong and must leave nothing at `path`."""
    try:
        write(path, *args, **kwargs)
    except (ValueError, OmnitofError) as err:
        assert str(err)
        assert not path.exists(), f"{path.name} left behind after: {err}"
        event("refused")
        return False
    event("written")
    return True


@st.composite
def trajectories(draw) -> Trajectory:
    n = draw(st.integers(1, 5))
    stamps = 1.7e9 + np.cumsum(draw(st.lists(st.floats(0.01, 10.0), min_size=n, max_size=n)))
    poses = np.array(draw(st.lists(st.tuples(st.floats(-100, 100), st.floats(-100, 100), st.floats(-3, 3)),
                                   min_size=n, max_size=n)))
    return Trajectory(poisoned(draw, stamps), poisoned(draw, poses))


@PROPERTY
@given(traj=trajectories())
def test_tum_trajectories_read_back_as_written(traj):
    from omnitof.io.tum import read_tum, write_tum

    with tempfile.TemporaryDirectory() as name:
        path = Path(name) / "t.tum"
        if not written_or_refused(write_tum, path, traj, sort=True):
            return
        back = read_tum(path)
        order = np.argsort(traj.timestamps, kind="stable")
        # One row per stamp as written (to the microsecond): the last pose of each, as documented.
        written = np.char.mod("%.6f", traj.timestamps[order])
        order = order[np.append(written[1:] != written[:-1], True)]
        np.testing.assert_allclose(back.timestamps, traj.timestamps[order], rtol=0, atol=1e-6)
        np.testing.assert_allclose(back.poses[:, :2], traj.poses[order, :2], rtol=1e-9, atol=1e-6)
        turn = np.angle(np.exp(1j * (back.poses[:, 2] - traj.poses[order, 2])))
        np.testing.assert_allclose(turn, 0.0, atol=1e-6)


@st.composite
def scan_fields(draw) -> tuple[dict, str]:
    """A ScanSequence's fields (some poisoned) and a hostname to write it with."""
    n, beams = draw(st.integers(1, 4)), draw(st.integers(1, 5))
    stamps = 1.7e9 + np.cumsum(draw(st.lists(st.floats(0.05, 1.0), min_size=n, max_size=n)))
    ranges = np.array(draw(st.lists(st.floats(0.0, 30.0), min_size=n * beams, max_size=n * beams))).reshape(n, beams)
    odometry = np.array(draw(st.lists(st.tuples(st.floats(-50, 50), st.floats(-50, 50), st.floats(-3, 3)),
                                      min_size=n, max_size=n)))
    with np.errstate(over="ignore"):  # 1e300 is inf in float32, as a reader's would be
        poisoned_ranges = np.float32(poisoned(draw, ranges))
    fields = dict(timestamps=poisoned(draw, stamps), ranges=poisoned_ranges,
                  angles=np.linspace(-1.0, 1.0, beams) if beams > 1 else np.zeros(1),
                  odometry=poisoned(draw, odometry), max_range=draw(st.one_of(st.just(20.0), HOSTILE)))
    hostname = draw(st.sampled_from(["omnitof", "robot-1", "my host", "", "a\tb", "é", "x:y"]))
    return fields, hostname


def scans_or_none(fields: dict) -> ScanSequence | None:
    """The scans of `fields`, or None where ScanSequence itself refuses the values (nothing to write)."""
    try:
        with np.errstate(invalid="ignore", over="ignore"):
            return ScanSequence(**fields)
    except (ValueError, OmnitofError):
        return None


@PROPERTY
@given(case=scan_fields())
def test_carmen_logs_read_back_as_written(case):
    from omnitof.io.carmen import read_carmen, write_carmen

    fields, hostname = case
    scans = scans_or_none(fields)
    if scans is None:
        return
    with tempfile.TemporaryDirectory() as name:
        path = Path(name) / "log.clf"
        if not written_or_refused(write_carmen, path, scans, hostname=hostname):
            return
        back = read_carmen(path).scans
        assert len(back) == len(scans)
        np.testing.assert_allclose(back.timestamps, scans.timestamps, rtol=0, atol=1e-6)
        np.testing.assert_allclose(back.odometry, scans.odometry, rtol=0, atol=1e-6)
        # Ranges are written to the millimetre, and CARMEN reads 0 (or less) and the maximum
        # range as no echo.
        written = np.round(scans.ranges.astype(np.float64), 3)
        echo = np.isfinite(written) & (written > 0.0) & (np.float32(written) < np.float32(round(scans.max_range, 3)))
        assert np.array_equal(np.isfinite(back.ranges), echo)
        np.testing.assert_allclose(back.ranges[echo], scans.ranges[echo], rtol=0, atol=5e-4 + 1e-6)


@st.composite
def occupancy_maps(draw) -> tuple[OccupancyMap, str]:
    rows, cols = draw(st.integers(1, 4)), draw(st.integers(1, 4))
    log_odds = np.array(draw(st.lists(st.floats(-5, 5), min_size=rows * cols, max_size=rows * cols)))
    known = np.array(draw(st.lists(st.booleans(), min_size=rows * cols, max_size=rows * cols)))
    resolution = draw(st.one_of(st.sampled_from([0.05, 0.1, 1e-4]), HOSTILE))
    origin = poisoned(draw, np.array([draw(st.floats(-1e4, 1e4)), draw(st.floats(-1e4, 1e4))]))
    name = draw(st.sampled_from(["map", "a b: c", "#m", "[m]", "m'q", 'm"q', "- m", "m&*!", "日本"]))
    occ = OccupancyMap(log_odds=log_odds.reshape(rows, cols), known=known.reshape(rows, cols),
                       resolution=resolution, origin=(float(origin[0]), float(origin[1])))
    return occ, name


@PROPERTY
@given(case=occupancy_maps())
def test_ros_maps_read_back_as_written(case):
    from omnitof.io.rosmap import read_ros_map, write_ros_map

    occ, name = case
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"{name}.yaml"
        if not written_or_refused(write_ros_map, path, occ):
            assert not path.with_suffix(".pgm").exists()
            return
        back = read_ros_map(path)
        assert back.log_odds.shape == occ.log_odds.shape
        assert back.resolution == occ.resolution and tuple(back.origin) == tuple(occ.origin)
        p = 1.0 / (1.0 + np.exp(-occ.log_odds))
        occupied, free = occ.known & (p > 0.65), occ.known & (p < 0.196)
        assert np.array_equal(back.known, occupied | free)
        assert np.array_equal(back.log_odds > 0, occupied)


@st.composite
def clouds(draw) -> tuple[np.ndarray, str, bool]:
    n = draw(st.integers(1, 5))
    points = poisoned(draw, np.array(draw(st.lists(st.floats(-1e3, 1e3), min_size=3 * n, max_size=3 * n))).reshape(n, 3))
    comment = draw(st.one_of(st.sampled_from(["", "end_header", "element vertex 9", "ply"]), st.text(max_size=12)))
    return points, comment, draw(st.booleans())


@PROPERTY
@given(case=clouds())
def test_ply_clouds_read_back_as_written(case):
    from omnitof.io.ply import read_ply, write_ply

    points, comment, binary = case
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "c.ply"
        if not written_or_refused(write_ply, path, points, binary=binary, comment=comment):
            return
        back, colours = read_ply(path)
        assert colours is None
        np.testing.assert_array_equal(back, points.astype(np.float32).astype(np.float64))


BAG = settings(PROPERTY, max_examples=int(40 * SCALE))  # a bag write and read take tens of ms


@BAG
@given(case=scan_fields(), version=st.sampled_from([1, 2]))
def test_laserscan_bags_read_back_as_written(case, version):
    from omnitof.io.rosbag import read_laserscan_bag, write_laserscan_bag

    scans = scans_or_none(case[0])
    if scans is None:
        return
    with tempfile.TemporaryDirectory() as name:
        path = Path(name) / ("scans.bag" if version == 1 else "scans")
        if not written_or_refused(write_laserscan_bag, path, scans, version=version):
            return
        back = read_laserscan_bag(path)
        assert len(back) == len(scans)
        np.testing.assert_allclose(back.timestamps, scans.timestamps, rtol=0, atol=1e-6)
        np.testing.assert_allclose(back.odometry[:, :2], scans.odometry[:, :2], rtol=0, atol=1e-6)
        turn = np.angle(np.exp(1j * (back.odometry[:, 2] - scans.odometry[:, 2])))
        np.testing.assert_allclose(turn, 0.0, atol=1e-6)
        # No echo stays no echo; every reading up to range_max comes back (float32), as ROS reads
        # LaserScan (only values beyond range_max are discarded).
        echo = np.isfinite(scans.ranges) & (scans.ranges > 0.0) & (scans.ranges <= np.float32(back.max_range))
        assert np.array_equal(np.isfinite(back.ranges) & (back.ranges > 0.0), echo)
        np.testing.assert_array_equal(back.ranges[echo], scans.ranges[echo])
