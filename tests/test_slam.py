"""The particle filter end to end: scan selection, trajectory filling, determinism, shared map
tiles, and SLAM on the simulated corridor loop against its ground truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnitof.errors import InputError
from omnitof.slam.config import load_config
from omnitof.eval.floorplan import wall_agreement
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.geometry import compose
from omnitof.sim.laser2d import corridor_loop_world
from omnitof.slam import fill_trajectory, run_slam, select_scans


def test_select_scans_by_distance_and_turn():
    # Straight 0.1 m steps, then a turn in place of 0.1 rad per step.
    straight = np.column_stack([np.arange(11) * 0.1, np.zeros(11), np.zeros(11)])
    turn = np.column_stack([np.full(6, 1.0), np.zeros(6), np.arange(1, 7) * 0.1])
    odom = np.vstack([straight, turn])
    chosen = select_scans(odom, linear=0.25, angular=math.radians(15))
    # 0 → 3 (0.3 m) → 6 → 9; then the turn: scan 12 is 0.2 rad from scan 9 (> 0.2618? no),
    # scan 13 is 0.3 rad > 15°, then 16 (0.6 rad, 0.3 from 13).
    assert chosen.tolist() == [0, 3, 6, 9, 13, 16]


def test_fill_trajectory_composes_odometry_after_each_corrected_pose():
    rng = np.random.default_rng(1)
    odom = np.cumsum(rng.normal(0, 0.1, (50, 3)), axis=0)
    integrated = np.array([0, 10, 25, 40])
    # Corrections: a different rigid shift at each integrated scan.
    shifts = rng.normal(0, 0.5, (4, 3))
    corrected = compose(shifts, odom[integrated])
    poses = fill_trajectory(odom, integrated, corrected)
    for k, start in enumerate(integrated):
        stop = integrated[k + 1] if k + 1 < len(integrated) else len(odom)
        assert np.allclose(poses[start:stop], compose(shifts[k], odom[start:stop]), atol=1e-12)


def small_run(scans, **filter_overrides):
    cfg = load_config(preset="sim2d", overrides={"filter": {"particles": 20, **filter_overrides}})
    return run_slam(scans, cfg)


def test_same_map_for_one_and_two_threads(corridor_loop):
    scans = corridor_loop.slice(0, 500)
    one = small_run(scans, threads=1, seed=4)
    two = small_run(scans, threads=2, seed=4)
    assert one.stats["resamplings"] > 0  # the comparison covers resampling, too
    assert np.array_equal(one.map.log_odds, two.map.log_odds)
    assert np.array_equal(one.map.known, two.map.known)
    assert np.array_equal(one.trajectory.poses, two.trajectory.poses)


def test_seed_fixes_the_result_and_changes_it(corridor_loop):
    scans = corridor_loop.slice(0, 300)
    a, b, c = small_run(scans, seed=1), small_run(scans, seed=1), small_run(scans, seed=2)
    assert np.array_equal(a.trajectory.poses, b.trajectory.poses)
    assert not np.array_equal(a.trajectory.poses, c.trajectory.poses)


def test_resampled_particles_share_map_tiles(corridor_loop):
    # Measured from the core's own allocation count: a map tile held by several particles is
    # one allocation. Without sharing, distinct tiles would equal referenced tiles.
    scans = corridor_loop.slice(0, 800)
    result = small_run(scans, particles=200)
    stats = result.stats
    assert stats["resamplings"] > 0
    # Each particle owns only the tiles it wrote since it was last copied (the latest scan's
    # tiles); everything older is shared. Measured here: under a quarter of the unshared size.
    assert stats["map_tiles_distinct"] < 0.25 * stats["map_tiles_referenced"]
    per_particle = stats["map_tiles_referenced"] / 200
    assert stats["map_tiles_distinct"] < per_particle + 200 * 0.3 * per_particle


def test_slam_beats_odometry_on_the_corridor_loop(corridor_loop):
    cfg = load_config(preset="sim2d")
    result = run_slam(corridor_loop, cfg)
    truth = corridor_loop.ground_truth
    slam = absolute_trajectory_error(result.trajectory.poses, truth)
    odom = absolute_trajectory_error(corridor_loop.odometry, truth)
    # Raw odometry misses the loop by about a metre; the filter closes it.
    assert odom.final > 0.8
    assert slam.mean < 0.35 * odom.mean
    assert slam.final < 0.15
    assert slam.heading_final_deg < 2.0
    # The map's walls lie on the true walls: most occupied cells within 10 cm of one.
    walls = wall_agreement(result.map, corridor_loop_world().distance_to_walls, tolerance=0.1)
    assert walls.occupied_cells > 1000
    assert walls.near_fraction > 0.6
    assert walls.median_distance < 0.1
    # One pose per scan, at the scans' own timestamps.
    assert np.array_equal(result.trajectory.timestamps, corridor_loop.timestamps)


_BARE_AISLES = """
name: bare_aisles
description: A 20 m x 6 m room around one 14 m block, two aisles with nothing along them.
ceiling_height: 2.5
walls:
  - points: [[0.0, 0.0], [20.0, 0.0], [20.0, 6.0], [0.0, 6.0]]
    closed: true
boxes:
  - {centre: [10.0, 3.0], size: [14.0, 1.0], height: 2.0}
path:
  waypoints: [[1.6, 1.2], [18.4, 1.2], [18.4, 4.8], [1.6, 4.8]]
"""


@pytest.mark.parametrize("seed", [0, 2])
def test_the_laser_preset_maps_a_short_range_lidars_aisles_to_their_length(tmp_path, seed):
    # A 360° lidar of 3.5 m (TurtleBot class) in a 2.5 m aisle sees two parallel walls and
    # nothing that ends them: the match alone decides the motion along them, and its pull
    # towards what the map has seen shortened the aisles (laser180-scanmatch without an odometry
    # prior: 0.62 and 0.39 m mean error in these two seeds, the raw odometry 0.64 and 0.48).
    # The Student-t odometry prior holds the pose there and gives way where wheels slip.
    from omnitof.sim.laser2d import beam_angles, simulate_scans
    from omnitof.sim.sequence import make_sequence
    from omnitof.sim.worlds import load_world
    from omnitof.types import ScanSequence

    (tmp_path / "bare_aisles.yaml").write_text(_BARE_AISLES)
    world = load_world(tmp_path / "bare_aisles.yaml")
    drive = make_sequence(world, seed=seed)
    angles = beam_angles(360, 360.0)
    ranges = simulate_scans(world.to_world2d(0.6), drive.ground_truth, angles, max_range=3.5, range_noise=0.015,
                            seed=np.random.default_rng([seed, 1]))
    scans = ScanSequence(timestamps=drive.timestamps, ranges=ranges, angles=angles, odometry=drive.odometry,
                         sensor_pose=np.zeros(3), max_range=3.5, ground_truth=drive.ground_truth)
    cfg = load_config(preset="laser180-scanmatch")
    assert cfg.scan_matcher.odometry_prior and cfg.scan_matcher.prior_dof == 3.0
    slam = absolute_trajectory_error(run_slam(scans, cfg).trajectory.poses, scans.ground_truth)
    odom = absolute_trajectory_error(scans.odometry, scans.ground_truth)
    assert odom.mean > 0.3
    assert slam.mean < 0.15, slam
    assert slam.final < 0.05, slam


def test_sensor_offset_is_honoured(corridor_loop):
    # The same scans, declared as taken by a sensor 0.3 m ahead and 0.1 rad to the left of the
    # robot centre, with the robot poses moved back accordingly. With noise-free motion the
    # filter must build the same map (up to rounding in a few cells).
    from omnitof.geometry import inverse
    from omnitof.types import ScanSequence

    offset = np.array([0.3, 0.05, 0.1])
    scans = corridor_loop.slice(0, 400)
    moved = ScanSequence(
        timestamps=scans.timestamps,
        ranges=scans.ranges,
        angles=scans.angles,
        odometry=compose(scans.odometry, inverse(offset)),
        sensor_pose=offset,
        max_range=scans.max_range,
    )
    still = {"alpha1": 0.0, "alpha2": 0.0, "alpha3": 0.0, "alpha4": 0.0}
    cfg = load_config(preset="sim2d", overrides={"filter": {"particles": 3}, "motion": still})
    base, shifted = run_slam(scans, cfg), run_slam(moved, cfg)
    assert base.map.log_odds.shape == shifted.map.log_odds.shape
    same = np.isclose(base.map.log_odds, shifted.map.log_odds, atol=1e-4)
    assert same.mean() > 0.999
    assert np.allclose(compose(base.trajectory.poses, inverse(offset)), shifted.trajectory.poses, atol=1e-9)


def test_empty_input_is_refused(corridor_loop):
    with pytest.raises(InputError, match="no scans"):
        run_slam(corridor_loop.slice(0, 0), load_config())


def test_scans_without_any_echo_are_refused_before_the_filter(corridor_loop):
    # Before, such a log "succeeded" with a 0 × 0 map that read_ros_map rejects. With
    # map.clear_no_echo the no-echo beams clear free space, and the map is not empty.
    scans = corridor_loop.slice(0, 40)
    scans.ranges[:] = np.inf
    with pytest.raises(InputError, match="no beam of the 40 scans has an echo"):
        run_slam(scans, load_config(preset="sim2d"))
    cleared = run_slam(scans, load_config(preset="sim2d", overrides={"map": {"clear_no_echo": True}}))
    assert cleared.map.known.any() and not (cleared.map.log_odds[cleared.map.known] > 0).any()


def interlaced_loop(loop):
    """The corridor loop seen by an interlaced laser (as the Freiburg hospital's SICK): 181 beams
    from -90°, then 180 beams from -89.75°, -89.5°, -89.25°, in turn, all at 1°."""
    from omnitof.sim.laser2d import simulate_scans
    from omnitof.types import ScanSequence, evenly_spaced_beams

    n = len(loop)
    offsets = np.radians([0.0, 0.75, 0.25, 0.5])[np.arange(n) % 4]
    counts = np.where(offsets == 0.0, 181, 180)
    full = -np.pi / 2 + offsets[:, None] + np.radians(1.0) * np.arange(181)  # one beam too many
    ranges = simulate_scans(corridor_loop_world(), loop.ground_truth, full, max_range=loop.max_range, seed=5)
    angles, beam_counts = evenly_spaced_beams(-np.pi / 2 + offsets, np.full(n, np.radians(1.0)), counts,
                                              tolerance=1e-9)
    return ScanSequence(loop.timestamps, ranges, angles, loop.odometry, max_range=loop.max_range,
                        ground_truth=loop.ground_truth, beam_counts=beam_counts)


def test_per_scan_geometry_shared_by_all_scans_gives_the_same_bytes(corridor_loop):
    from omnitof.types import ScanSequence

    scans = corridor_loop.slice(0, 400)
    tiled = ScanSequence(scans.timestamps, scans.ranges, np.tile(scans.angles, (len(scans), 1)),
                         scans.odometry, max_range=scans.max_range)
    assert tiled.per_scan_geometry  # so every step hands the filter the scan's own angles
    for proposal in ("odometry", "scanmatch"):
        fixed, own = (small_run(s, seed=3, proposal=proposal) for s in (scans, tiled))
        assert fixed.stats["resamplings"] > 0
        assert np.array_equal(fixed.map.log_odds, own.map.log_odds)
        assert np.array_equal(fixed.trajectory.poses, own.trajectory.poses)


def test_slam_with_an_interlaced_laser(corridor_loop):
    scans = interlaced_loop(corridor_loop)
    assert set(scans.beam_counts) == {180, 181}
    result = run_slam(scans, load_config(preset="sim2d"))
    slam = absolute_trajectory_error(result.trajectory.poses, scans.ground_truth)
    odom = absolute_trajectory_error(scans.odometry, scans.ground_truth)
    assert slam.mean < 0.35 * odom.mean and slam.final < 0.15
    walls = wall_agreement(result.map, corridor_loop_world().distance_to_walls, tolerance=0.1)
    assert walls.near_fraction > 0.6 and walls.median_distance < 0.1


def test_interlaced_laser_same_result_for_one_and_two_threads(corridor_loop):
    scans = interlaced_loop(corridor_loop).slice(0, 500)
    one = small_run(scans, threads=1, seed=4)
    two = small_run(scans, threads=2, seed=4)
    assert one.stats["resamplings"] > 0
    assert np.array_equal(one.map.log_odds, two.map.log_odds)
    assert np.array_equal(one.trajectory.poses, two.trajectory.poses)


def test_filter_step_checks_a_scans_own_angles(corridor_loop):
    from omnitof import _core
    from omnitof.slam.driver import _make_filter

    scans = corridor_loop.slice(0, 2)
    pf = _make_filter(scans, load_config(preset="sim2d"))
    pose = scans.odometry[0]
    with pytest.raises(ValueError, match="scan has 181 ranges but 180 angles"):
        pf.step(pose, pose, scans.scan_ranges(0), 0, angles=scans.angles[:180])
    with pytest.raises(ValueError, match="angles must be finite"):
        pf.step(pose, pose, scans.scan_ranges(0), 0, angles=np.full(181, np.nan))
    with pytest.raises(ValueError, match="the filter was made for 181"):
        pf.step(pose, pose, scans.scan_ranges(0)[:180], 0)
    pf.step(pose, pose, scans.scan_ranges(0)[:180], 0, angles=scans.angles[1:])  # its own beams
    assert pf.steps == 1 and isinstance(pf, _core.ParticleFilter)


_LONG_CORRIDOR = """
name: long_corridor
description: A bare corridor 40 m long and 5 m wide, nothing along it but its two ends.
ceiling_height: 2.5
walls:
  - points: [[0.0, 0.0], [40.0, 0.0], [40.0, 5.0], [0.0, 5.0]]
    closed: true
path:
  waypoints: [[1.5, 1.5], [38.5, 1.5], [38.5, 3.5], [1.5, 3.5]]
"""


def test_the_laser_preset_holds_a_long_corridor_by_its_far_end(tmp_path):
    # A laser of 80 m down a bare 40 m corridor: only the end wall ahead, up to 38 m away, says
    # where along the corridor the robot is. Matched and mapped only to 15 and 20 m (the laser
    # preset before the forty-fourth session), the run was no better than its odometry: 1.02 m
    # mean error against the wheels' 1.12 m (seed 0; 0.97 and 0.95 m in seeds 1 and 2); with
    # the readings to 40 m, 0.23 m.
    from omnitof.sim.laser2d import beam_angles, simulate_scans
    from omnitof.sim.sequence import make_sequence
    from omnitof.sim.worlds import load_world
    from omnitof.types import ScanSequence

    (tmp_path / "long_corridor.yaml").write_text(_LONG_CORRIDOR)
    world = load_world(tmp_path / "long_corridor.yaml")
    drive = make_sequence(world, seed=0)
    angles = beam_angles(181, 180.0)
    ranges = simulate_scans(world.to_world2d(0.6), drive.ground_truth, angles, max_range=80.0, range_noise=0.01,
                            seed=np.random.default_rng([0, 1]))
    scans = ScanSequence(timestamps=drive.timestamps, ranges=ranges, angles=angles, odometry=drive.odometry,
                         sensor_pose=np.zeros(3), max_range=80.0, ground_truth=drive.ground_truth)
    cfg = load_config(preset="laser180-scanmatch")
    assert cfg.sensor_model.max_range >= 38.5 and cfg.map.max_range >= 38.5
    slam = absolute_trajectory_error(run_slam(scans, cfg).trajectory.poses, scans.ground_truth)
    odom = absolute_trajectory_error(scans.odometry, scans.ground_truth)
    assert odom.mean > 0.8
    assert slam.mean < 0.4, slam
