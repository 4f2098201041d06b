"""Odometry far from its own origin (georeferenced, UTM-scale): the filters run in a frame moved
next to the robot and hand back every result in the odometry's frame (omnitof.slam.anchor,
omnitof.map3d.voxels notes), and odometry too far out for float64 to hold its motions is refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from omnitof.errors import InputError
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.map3d import VoxelMap
from omnitof.slam import check_limits, run_slam
from omnitof.slam.config import load_config

# 50 000 km east and 30 000 km south: at 0.01 m, 5e9 cells from the origin, beyond the 2^30 that
# the core's grids address (the run failed there before it was moved).
FAR = np.array([5e7, -3e7])


def _far(scans, shift):
    move = np.array([shift[0], shift[1], 0.0])
    return dataclasses.replace(scans, odometry=scans.odometry + move, ground_truth=scans.ground_truth + move)


@pytest.fixture(scope="module")
def loop(corridor_loop):
    return corridor_loop.slice(0, 300)


@pytest.mark.parametrize("backend", [False, True])
def test_odometry_far_out_maps_at_a_fine_resolution_as_near_the_origin(loop, backend):
    cfg = load_config(preset="sim2d", overrides={"filter": {"particles": 10, "seed": 1}, "map": {"resolution": 0.01},
                                                 "backend": {"enabled": backend}})
    near, far = run_slam(loop, cfg), run_slam(_far(loop, FAR), cfg)
    # The same run: only float64 rounding of the far poses (1e-8 m at 5e7 m) tells them apart.
    moved = far.trajectory.poses - near.trajectory.poses
    assert np.abs(moved[:, :2] - FAR).max() < 1e-6 and np.abs(moved[:, 2]).max() < 1e-6
    assert np.array_equal(far.odometry.poses, _far(loop, FAR).odometry)
    assert np.subtract(far.map.origin, near.map.origin) == pytest.approx(FAR, abs=1e-6)
    assert far.map.log_odds.shape == near.map.log_odds.shape
    differ = np.sum(far.map.known != near.map.known) + np.sum(np.abs(far.map.log_odds - near.map.log_odds) > 1e-3)
    assert differ < 1e-3 * near.map.known.sum()
    err = absolute_trajectory_error(far.trajectory.poses, _far(loop, FAR).ground_truth).mean
    assert err == pytest.approx(absolute_trajectory_error(near.trajectory.poses, loop.ground_truth).mean, abs=1e-6)
    if backend:
        assert np.abs(far.graph["nodes"][:, :2] - near.graph["nodes"][:, :2] - FAR).max() < 1e-6


def test_odometry_too_far_out_to_hold_its_motions_is_refused(loop):
    cfg = load_config(preset="sim2d")
    # At 1e12 m a float64 position holds steps of 1.2e-4 m, more than a thousandth of 0.05 m.
    far = _far(loop.slice(0, 10), (1e12, 0.0))
    with pytest.raises(InputError, match=r"odometry pose of scan 0 lies at \(1e\+12, .*steps of 0.000122 m"):
        check_limits(far, cfg)
    check_limits(_far(loop.slice(0, 10), (1e10, 0.0)), cfg)  # steps of 2e-6 m: fine


def test_a_carmen_log_in_utm_coordinates_runs_from_the_command_line(tmp_path, loop, capsys):
    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen
    from omnitof.io.tum import read_tum

    path = tmp_path / "utm.log"
    write_carmen(path, _far(loop.slice(0, 60), (4.3e6, 5.5e6)))
    out = tmp_path / "out"
    code = main(["slam", str(path), "--out", str(out), "--preset", "sim2d", "--particles", "5", "--quiet",
                 "--scan-delay", "0", "--set", "map.resolution=0.005", "--set", "backend.enabled=false"])
    assert code == 0, capsys.readouterr().err
    poses = read_tum(out / "trajectory.tum").poses
    assert np.abs(poses[:, :2] - loop.odometry[:60, :2] - (4.3e6, 5.5e6)).max() < 0.5
    origin = [float(v) for v in (out / "map.yaml").read_text().split("origin:")[1].split("]")[0].strip(" [").split(",")]
    assert 4.3e6 - 20 < origin[0] < 4.3e6 + 20 and 5.5e6 - 20 < origin[1] < 5.5e6 + 20


def _room_rays():
    """Rays (origins, end points) of one frame in the robot frame: a ring of walls 3 m away,
    from 0.1 m to 2 m high."""
    bearing = np.radians(np.arange(0, 360, 2.0))
    height = np.linspace(0.1, 2.0, 12)
    b, h = np.meshgrid(bearing, height)
    ends = np.column_stack([3.0 * np.cos(b.ravel()), 3.0 * np.sin(b.ravel()), h.ravel()])
    origins = np.column_stack([0.05 * np.cos(b.ravel()), 0.05 * np.sin(b.ravel()), np.full(b.size, 0.3)])
    return origins, ends


def test_a_voxel_map_far_out_keeps_its_voxels():
    origins, ends = _room_rays()
    # 2^20 m out: 8.4 million voxels of 0.125 m, beyond the core's ±2^20 (the map refused such
    # rays before). Both numbers are exact in binary, so the moved voxels are the same.
    shift = np.array([2.0**20, -(2.0**19), 0.0])
    near, far = VoxelMap(resolution=0.125), VoxelMap(resolution=0.125)
    for pose in ([0.4, 0.2, 0.3], [1.1, -0.3, 1.0]):
        near.integrate_frame(np.array(pose), origins, ends)
        far.integrate_frame(np.array(pose) + shift, origins, ends)
    assert len(near.occupied()) > 500
    assert np.array_equal(far.occupied() - shift, near.occupied())
    lo_near, hi_near = near.bounds()
    lo_far, hi_far = far.bounds()
    assert np.array_equal(lo_far - shift, lo_near) and np.array_equal(hi_far - shift, hi_near)
    probe = near.occupied()[:50]
    assert np.array_equal(far.log_odds_at(probe + shift), near.log_odds_at(probe))
