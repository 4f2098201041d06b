"""Tests of the 2D laser world (omnitof.sim.laser2d): each checks a computed answer."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from omnitof.errors import ConfigError
from omnitof.geometry import compose, wrap_angle
from omnitof.sim import laser2d
from omnitof.sim.laser2d import (
    Walker,
    World2D,
    beam_angles,
    corridor_loop_world,
    loop_path,
    make_loop_dataset,
    plan_path,
    simulate_odometry,
    simulate_scans,
    walkers_beside,
)
from omnitof.types import ScanSequence

# A square room of half-width H around C, used by the raycast and scan tests.
H = 2.0
C = np.array([0.5, -0.3])


def square_room(centre: np.ndarray = C, half: float = H) -> World2D:
    corners = centre + half * np.array([[-1, -1], [1, -1], [1, 1], [-1, 1], [-1, -1]], float)
    return World2D.from_polylines([corners])


def box_exit_distance(origin: np.ndarray, angles: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Distance from a point inside an axis-aligned box to its boundary (the slab method).

    Independent of the segment intersection: along each axis, the ray reaches the bound it is
    heading for after (bound - origin) / direction; the nearest of the two axes is the exit.
    """
    d = np.stack([np.cos(angles), np.sin(angles)], axis=-1)
    with np.errstate(divide="ignore"):
        bound = np.where(d > 0, hi, lo)
        t = np.where(d != 0, (bound - origin) / d, np.inf)
    return t.min(axis=-1)


# ---------------------------------------------------------------------------------- raycast


def test_raycast_from_centre_is_half_width_over_cosine():
    angles = np.linspace(-math.pi, math.pi, 721)
    got = square_room().raycast(C[None], angles[None])[0]
    # The wall a ray hits is the one its direction points at most: x walls where |cos| >= |sin|.
    expected = H / np.maximum(np.abs(np.cos(angles)), np.abs(np.sin(angles)))
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def test_raycast_off_centre_matches_slab_method():
    rng = np.random.default_rng(3)
    origins = C + rng.uniform(-1.9, 1.9, size=(50, 2))
    angles = rng.uniform(-math.pi, math.pi, size=(50, 37))
    got = square_room().raycast(origins, angles)
    expected = box_exit_distance(origins[:, None, :], angles, C - H, C + H)
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)


def test_raycast_corners_do_not_leak():
    # From the centre, the 45 deg rays end exactly on the shared end points of two walls.
    angles = np.array([1, 3, 5, 7]) * math.pi / 4
    got = square_room().raycast(C[None], angles[None])[0]
    np.testing.assert_allclose(got, H * math.sqrt(2.0), rtol=0, atol=1e-9)


def test_raycast_segment_end_points_and_misses():
    wall = World2D(np.array([[[1.0, -1.0], [1.0, 1.0]]]))
    origin = np.zeros((1, 2))
    corner = math.atan2(1.0, 1.0)
    angles = np.array([[
        0.0,  # straight at the middle: 1 m
        corner,  # exactly through the upper end point: sqrt(2) m
        -corner,  # the lower end point
        corner + 1e-6,  # just past the end point: a miss
        math.pi,  # away from the wall: a miss (the hit would be behind the origin)
        math.pi / 2,  # parallel to the wall: a miss
    ]])
    got = wall.raycast(origin, angles)[0]
    np.testing.assert_allclose(got[:3], [1.0, math.sqrt(2.0), math.sqrt(2.0)], rtol=0, atol=1e-9)
    assert np.all(np.isinf(got[3:]))


def test_raycast_outside_the_room_looking_away_misses():
    outside = C + np.array([5.0, 0.0])
    got = square_room().raycast(outside[None], np.array([[0.0, math.pi / 2, -math.pi / 4]]))
    assert np.all(np.isinf(got))
    # Looking back at the room, it sees the near wall.
    back = square_room().raycast(outside[None], np.array([[math.pi]]))
    assert back[0, 0] == pytest.approx(5.0 - H, abs=1e-9)


def test_raycast_max_range_and_chunking_do_not_change_hits(monkeypatch):
    world = corridor_loop_world()
    poses = loop_path().poses[::7]
    angles = poses[:, 2:3] + beam_angles(91, 360.0)
    full = world.raycast(poses[:, :2], angles)
    monkeypatch.setattr(laser2d, "_PAIR_BUDGET", 3000)  # forces chunks of a single origin
    near = world.raycast(poses[:, :2], angles, max_range=5.0)
    expected = np.where(full <= 5.0, full, np.inf)
    np.testing.assert_array_equal(near, expected)
    assert np.isfinite(near).mean() > 0.5  # the comparison is about real hits


def test_world_rejects_degenerate_input():
    with pytest.raises(ValueError, match="zero length"):
        World2D(np.array([[[1.0, 1.0], [1.0, 1.0]]]))
    with pytest.raises(ValueError, match="shape"):
        World2D.from_polylines([np.zeros((1, 2))])


# ------------------------------------------------------------------------- distance_to_walls


def test_distance_to_walls_hand_computed():
    world = World2D.from_polylines([np.array([[0.0, 0.0], [2.0, 0.0]]),
                                    np.array([[5.0, -1.0], [5.0, 1.0]])])
    points = np.array([
        [1.0, 1.0],  # above the middle of the first wall: 1
        [3.0, 1.0],  # beyond its end (2, 0): sqrt(2)
        [-1.0, 0.0],  # on its line, before its start: 1
        [1.5, 0.0],  # on it: 0
        [4.0, 0.5],  # beside the second wall: 1
        [3.5, 0.0],  # midway between (2, 0) and x = 5: 1.5
        [6.0, 3.0],  # beyond the second wall's end (5, 1): sqrt(1 + 4)
    ])
    expected = [1.0, math.sqrt(2.0), 1.0, 0.0, 1.0, 1.5, math.sqrt(5.0)]
    np.testing.assert_allclose(world.distance_to_walls(points), expected, rtol=0, atol=1e-12)


# ----------------------------------------------------------------------------------- world


def test_corridor_loop_world_has_its_dimensions_and_clear_corridors():
    world = corridor_loop_world()
    xmin, xmax, ymin, ymax = world.bounds
    # The outer wall is at -2 / 18 / 12 (16 x 10 block + 2 m corridors); niches, alcoves and the
    # 4 m room (with its 0.2 m partition) reach beyond it.
    assert (xmin, xmax, ymin, ymax) == pytest.approx((-3.2, 22.2, -3.0, 12.8))
    np.testing.assert_array_equal(world.segments, corridor_loop_world().segments)  # deterministic
    # The robot's path keeps at least 0.6 m from every wall, box and pillar.
    assert world.distance_to_walls(loop_path().poses[:, :2]).min() >= 0.6 - 1e-9


def test_corridor_features_make_every_pose_distinguishable_along_the_corridor():
    """Moving 0.3 m forward must change a good share of the beams, at every pose of the loop.

    In a bare corridor the beams that hit the side walls do not change at all under a shift
    along its axis, so a scan matcher cannot tell where along the corridor it is.
    """
    poses = loop_path().poses
    angles = beam_angles(181, 180.0)
    ahead = compose(poses, np.array([0.3, 0.0, 0.0]))

    def changed_share(world: World2D) -> np.ndarray:
        here = world.raycast(poses[:, :2], poses[:, 2:3] + angles, max_range=8.0)
        there = world.raycast(ahead[:, :2], ahead[:, 2:3] + angles, max_range=8.0)
        with np.errstate(invalid="ignore"):
            differ = ~(np.abs(here - there) <= 0.05)  # inf vs finite also counts as changed
        differ &= np.isfinite(here) | np.isfinite(there)
        return differ.mean(axis=1)

    assert changed_share(corridor_loop_world()).min() > 0.10
    assert changed_share(corridor_loop_world(features=False)).min() == 0.0


def test_corridor_loop_world_rejects_a_block_too_small_for_its_features():
    with pytest.raises(ConfigError):
        corridor_loop_world(block_width=4.0, block_height=3.0)


# ------------------------------------------------------------------------------------ path


def test_plan_path_l_turn_matches_arc_geometry():
    speed, rate, turn_rate = 0.5, 20.0, 0.5
    r = speed / turn_rate  # 1 m
    path = plan_path(np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]]), speed, rate, turn_rate)
    assert path.length == pytest.approx(10.0 - 2 * r + math.pi * r / 2, abs=1e-12)
    # On the arc the robot is r from the centre (5 - r, r) and faces along the tangent.
    on_arc = (path.poses[:, 2] > 0.01) & (path.poses[:, 2] < math.pi / 2 - 0.01)
    assert on_arc.sum() > 10
    rel = path.poses[on_arc, :2] - [5.0 - r, r]
    np.testing.assert_allclose(np.hypot(rel[:, 0], rel[:, 1]), r, atol=1e-12)
    bearing_from_centre = np.arctan2(rel[:, 1], rel[:, 0])
    np.testing.assert_allclose(bearing_from_centre, path.poses[on_arc, 2] - math.pi / 2, atol=1e-12)



def test_a_path_of_many_laps_is_sampled_piece_by_piece_without_a_jump():
    """200 laps of a 6 m square (1600 pieces, 30 000 poses): every pose lies on its own piece,
    so the path moves one step and turns at most the turn rate between poses, and every lap's
    corners lie on the same arcs. (Sampling looped over the pieces, each over every sample: a
    world of 10 000 laps took minutes.)"""
    speed, rate, turn_rate = 0.4, 10.0, 0.6
    r = speed / turn_rate
    square = np.array([[0.0, 0.0], [6.0, 0.0], [6.0, 6.0], [0.0, 6.0]])
    path = plan_path(np.vstack([np.tile(square, (200, 1)), square[:1]]), speed, rate, turn_rate)
    step = speed / rate
    moved = np.hypot(*np.diff(path.poses[:, :2], axis=0).T)
    assert moved.max() <= step + 1e-9 and moved.min() > 0.99 * step
    assert np.abs(wrap_angle(np.diff(path.poses[:, 2]))).max() <= turn_rate / rate + 1e-9
    # Every pose in the corner (6, 0)'s quarter: on the arc about (6 - r, r), every lap alike.
    corner = (path.poses[:, 0] > 6.0 - r) & (path.poses[:, 1] < r)
    assert corner.sum() > 200 * 5
    np.testing.assert_allclose(np.hypot(*(path.poses[corner, :2] - [6.0 - r, r]).T), r, atol=1e-9)

def test_loop_path_respects_speed_and_turn_rate_and_closes():
    speed, rate, turn_rate = 0.4, 10.0, 0.6
    path = loop_path(speed=speed, rate_hz=rate, max_turn_rate=turn_rate, overlap=5.0)
    step = speed / rate
    moved = np.hypot(*np.diff(path.poses[:, :2], axis=0).T)
    turned = np.abs(wrap_angle(np.diff(path.poses[:, 2])))
    np.testing.assert_allclose(np.diff(path.timestamps), 1.0 / rate, atol=1e-12)
    assert moved.max() <= step + 1e-12  # chords of an arc are shorter than the arc
    assert moved.min() > 0.99 * step
    assert turned.max() <= turn_rate / rate + 1e-12  # also: headings never jump
    # Turns in total: one full counter-clockwise turn.
    assert np.sum(wrap_angle(np.diff(path.poses[:, 2]))) == pytest.approx(2 * math.pi, abs=1e-9)
    # After the loop the robot passes its start pose again, then drives 5 m past it.
    start = path.poses[0]
    later = path.poses[len(path.poses) // 2:]
    nearest = later[np.argmin(np.hypot(*(later[:, :2] - start[:2]).T))]
    assert np.hypot(*(nearest[:2] - start[:2])) <= step / 2 + 1e-9
    assert wrap_angle(nearest[2] - start[2]) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(path.poses[-1], start + [5.0, 0.0, 0.0], atol=step)
    print(f"loop path: {path.length:.2f} m, {len(path.poses)} poses, {path.timestamps[-1]:.1f} s")


def test_plan_path_refuses_waypoints_that_are_not_finite_or_too_far():
    with pytest.raises(ConfigError, match=r"waypoints must be finite, got \[nan, 1.0\]"):
        plan_path(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    # 1e300 m: an infinite length, which int() refused with a bare OverflowError.
    with pytest.raises(ConfigError, match="the path is inf m long"):
        plan_path(np.array([[0.0, 0.0], [1e300, 0.0]]))


def test_plan_path_refuses_a_turn_radius_the_rate_limit_forbids():
    with pytest.raises(ConfigError, match="max_turn_rate"):
        plan_path(np.array([[0.0, 0.0], [5.0, 0.0], [5.0, 5.0]]), 0.4, 10.0, 0.6, turn_radius=0.5)


# -------------------------------------------------------------------------------- odometry


def straight_line(n_steps: int, step: float) -> np.ndarray:
    """Poses along a straight line heading 30 deg, step metres apart."""
    heading = math.radians(30.0)
    s = np.arange(n_steps + 1) * step
    return np.stack([1.0 + s * math.cos(heading), -2.0 + s * math.sin(heading),
                     np.full_like(s, heading)], axis=1)


def test_odometry_without_errors_is_ground_truth():
    gt = loop_path().poses
    odo = simulate_odometry(gt, seed=1, alphas=(0.0, 0.0, 0.0, 0.0), wheel_radius_error=0.0,
                            wheel_base_error=0.0, heading_drift=0.0)
    np.testing.assert_allclose(odo[:, :2], gt[:, :2], rtol=0, atol=1e-9)
    np.testing.assert_allclose(wrap_angle(odo[:, 2] - gt[:, 2]), 0.0, atol=1e-9)


def test_odometry_systematic_errors_have_their_analytic_effect():
    gt = loop_path()
    no_noise = (0.0, 0.0, 0.0, 0.0)
    # A wheel-base error scales every turn: after one full turn the heading is 2 pi eps off; the
    # drift adds its rate times the distance driven (the sum of the sampled steps).
    eps, drift = 0.02, math.radians(0.1)
    odo = simulate_odometry(gt.poses, seed=0, alphas=no_noise, wheel_radius_error=0.0,
                            wheel_base_error=eps, heading_drift=drift)
    driven = np.hypot(*np.diff(gt.poses[:, :2], axis=0).T).sum()
    expected = 2 * math.pi * eps + drift * driven
    assert wrap_angle(odo[-1, 2] - gt.poses[-1, 2]) == pytest.approx(expected, abs=1e-6)
    # A wheel-radius error scales distances.
    line = straight_line(100, 0.05)
    odo = simulate_odometry(line, seed=0, alphas=no_noise, wheel_radius_error=0.03,
                            wheel_base_error=0.0, heading_drift=0.0)
    np.testing.assert_allclose(odo[-1, :2] - odo[0, :2], 1.03 * (line[-1, :2] - line[0, :2]),
                               atol=1e-12)


def test_default_odometry_is_clearly_wrong_after_the_loop():
    gt = loop_path().poses
    odo = simulate_odometry(gt, seed=0)
    assert np.array_equal(odo[0], gt[0])
    end_error = float(np.hypot(*(odo[-1, :2] - gt[-1, :2])))
    heading_error = math.degrees(abs(wrap_angle(odo[-1, 2] - gt[-1, 2])))
    print(f"default odometry, seed 0: end error {end_error:.2f} m, heading {heading_error:.1f} deg")
    # Measured: 1.29 m and 9.7 deg (the systematic part alone gives 1.16 m and 8.6 deg).
    assert end_error > 0.5
    assert heading_error > 4.0


def test_odometry_noise_statistics_match_the_alphas():
    """Over many seeds, a straight run's odometry length spread is sqrt(n alpha3) * step and its
    heading spread is sqrt(2 n alpha2) * step (rot1 and rot2 each get alpha2 trans^2)."""
    n, step, a2, a3 = 40, 0.05, 0.004, 0.01
    line = straight_line(n, step)
    lengths, headings = [], []
    for seed in range(1500):
        odo = simulate_odometry(line, seed=seed, alphas=(0.0, a2, a3, 0.0),
                                wheel_radius_error=0.0, wheel_base_error=0.0, heading_drift=0.0)
        lengths.append(np.hypot(*np.diff(odo[:, :2], axis=0).T).sum())
        headings.append(wrap_angle(odo[-1, 2] - line[-1, 2]))
    lengths, headings = np.array(lengths), np.array(headings)
    sigma_len = math.sqrt(n * a3) * step
    sigma_heading = math.sqrt(2 * n * a2) * step
    # 1500 samples: the standard deviation is known to ~2 %, the mean to ~3 % of sigma.
    assert lengths.std() == pytest.approx(sigma_len, rel=0.08)
    assert lengths.mean() == pytest.approx(n * step, abs=0.15 * sigma_len)
    assert headings.std() == pytest.approx(sigma_heading, rel=0.08)
    assert headings.mean() == pytest.approx(0.0, abs=0.15 * sigma_heading)


# ----------------------------------------------------------------------------------- scans


def centre_poses(n: int) -> np.ndarray:
    return np.tile([C[0], C[1], 0.3], (n, 1))


def test_scan_noise_matches_range_noise():
    angles = beam_angles(181, 180.0)
    poses = centre_poses(300)
    ranges = simulate_scans(square_room(), poses, angles, max_range=10.0, range_noise=0.02, seed=4)
    assert ranges.dtype == np.float32
    truth = H / np.maximum(np.abs(np.cos(0.3 + angles)), np.abs(np.sin(0.3 + angles)))
    error = ranges.astype(np.float64) - truth
    assert error.std() == pytest.approx(0.02, rel=0.03)
    assert abs(error.mean()) < 0.001


def test_scan_max_range_and_dropout_give_inf():
    angles = beam_angles(360, 360.0)
    truth = H / np.maximum(np.abs(np.cos(0.3 + angles)), np.abs(np.sin(0.3 + angles)))
    ranges = simulate_scans(square_room(), centre_poses(50), angles, max_range=2.5,
                            range_noise=0.01, seed=5)
    assert np.all(np.isinf(ranges[:, truth > 2.56]))
    assert np.all(np.isfinite(ranges[:, truth < 2.44]))
    dropped = simulate_scans(square_room(), centre_poses(200), angles, max_range=10.0,
                             dropout=0.25, seed=6)
    assert np.isinf(dropped).mean() == pytest.approx(0.25, abs=0.01)


def test_scans_are_deterministic_for_a_seed():
    angles = beam_angles(181, 180.0)
    poses = loop_path().poses[:40]
    world = corridor_loop_world()
    a = simulate_scans(world, poses, angles, dropout=0.1, seed=7)
    b = simulate_scans(world, poses, angles, dropout=0.1, seed=7)
    c = simulate_scans(world, poses, angles, dropout=0.1, seed=8)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)


def test_scans_start_at_the_sensor_pose():
    robot = np.array([[C[0], C[1], 0.0]])
    sensor = (0.5, 0.0, math.pi / 2)  # 0.5 m ahead of the robot, looking to its left
    ranges = simulate_scans(square_room(), robot, np.array([0.0, math.pi / 2]),
                            sensor_pose=sensor, range_noise=0.0, seed=0)
    # The sensor's +x is the world's +y: the wall at y = C + H; its +y is the world's -x.
    np.testing.assert_allclose(ranges[0], [H, H + 0.5], atol=1e-6)


def marched_distance(origin, bearing, centre, radius, step=1e-4, reach=10.0):
    """Where a ray first enters a disc, found by walking along it in small steps: independent
    of the closed-form root that `simulate_scans` takes."""
    t = np.arange(0.0, reach, step)
    points = origin + t[:, None] * np.array([math.cos(bearing), math.sin(bearing)])
    inside = np.hypot(*(points - centre).T) <= radius
    return t[np.argmax(inside)] if inside.any() else math.inf


def test_people_occlude_the_walls_where_a_ray_walk_meets_them():
    robot = np.array([[C[0], C[1], 0.0], [C[0], C[1], 0.7]])
    angles = np.linspace(-0.4, 0.4, 41)
    people = np.array([[[C[0] + 1.2, C[1] + 0.1], [np.nan, np.nan]],
                       [[C[0] + 0.8, C[1] + 1.0], [C[0] - 1.0, C[1] - 1.0]]])
    ranges = simulate_scans(square_room(), robot, angles, people=people, person_radius=0.25,
                            range_noise=0.0, seed=0).astype(np.float64)
    walls = simulate_scans(square_room(), robot, angles, range_noise=0.0, seed=0).astype(np.float64)
    hits = 0
    for i, pose in enumerate(robot):
        for b, angle in enumerate(angles):
            nearest = min([marched_distance(pose[:2], pose[2] + angle, c, 0.25)
                           for c in people[i] if np.all(np.isfinite(c))], default=math.inf)
            expected = min(nearest, walls[i, b])
            hits += nearest < walls[i, b]
            assert ranges[i, b] == pytest.approx(expected, abs=2e-4), (i, b)
    assert hits > 10  # the people stand in the way of some beams, not all


def test_people_cast_in_chunks_is_cast_at_once(monkeypatch):
    walkers = (Walker(ahead=1.5, left=0.0, start=0.0, stop=8.0), Walker(ahead=1.0, left=0.6, start=3.0, stop=6.0))
    whole = make_loop_dataset(seed=1, walkers=walkers).ranges[:100]
    monkeypatch.setattr(laser2d, "_PAIR_BUDGET", 50)  # a few scans per chunk
    np.testing.assert_array_equal(make_loop_dataset(seed=1, walkers=walkers).ranges[:100], whole)


def test_walkers_keep_their_place_beside_the_robot_within_their_time():
    poses = np.array([[1.0, 2.0, 0.0], [1.5, 2.0, math.pi / 2], [2.0, 2.5, math.pi]])
    t = np.array([0.0, 1.0, 2.0])
    centres = walkers_beside(poses, t, [Walker(ahead=1.0, left=0.5, start=0.5, stop=2.0)])
    assert np.all(np.isnan(centres[0]))
    np.testing.assert_allclose(centres[1, 0], [1.5 - 0.5, 2.0 + 1.0])  # facing +y: ahead is +y, left is -x
    np.testing.assert_allclose(centres[2, 0], [2.0 - 1.0, 2.5 - 0.5])  # facing -x: left is -y


@pytest.mark.parametrize("bad", [dict(ahead=math.nan), dict(left=math.inf), dict(start=5.0, stop=4.0)])
def test_a_walker_out_of_bounds_is_refused_by_name(bad):
    fields = dict(ahead=1.0, left=0.5, start=0.0, stop=10.0) | bad
    with pytest.raises(ConfigError, match="Walker"):
        Walker(**fields)


def test_a_wider_loop_keeps_the_robot_in_its_corridors():
    data = make_loop_dataset(seed=0, block_width=40.0, block_height=20.0, corridor_width=3.5,
                             max_range=15.0, rate_hz=2.0)
    world = corridor_loop_world(40.0, 20.0, 3.5)
    # The path runs along the corridors' centre lines; boxes stand at most 0.4 m into them.
    assert world.distance_to_walls(data.ground_truth[:, :2]).min() >= 1.75 - 0.4 - 1e-9
    assert data.ground_truth[:, 0].max() == pytest.approx(40.0 + 1.75, abs=0.05)
    assert np.nanmax(np.where(np.isfinite(data.ranges), data.ranges, np.nan)) < 15.0
    np.testing.assert_allclose(np.diff(data.timestamps), 0.5)


def test_loop_walkers_only_shorten_the_scans_of_their_time():
    walkers = (Walker(ahead=1.5, left=0.0, start=10.0, stop=20.0),)
    plain, walked = make_loop_dataset(seed=3), make_loop_dataset(seed=3, walkers=walkers)
    during = (plain.timestamps >= 10.0) & (plain.timestamps <= 20.0)
    np.testing.assert_array_equal(walked.ranges[~during], plain.ranges[~during])
    np.testing.assert_array_equal(walked.odometry, plain.odometry)
    a, b = plain.ranges[during].astype(np.float64), walked.ranges[during].astype(np.float64)
    changed = a != b
    # A person 1.5 m straight ahead is seen in every scan, at 1.25 m for the middle beam, and
    # never makes a beam longer (the same noise draw is added to a shorter true distance).
    assert changed.any(axis=1).all()
    assert np.all(b[changed] < a[changed])
    middle = walked.n_beams // 2
    assert np.median(b[:, middle]) == pytest.approx(1.25, abs=0.01)


# --------------------------------------------------------------------------------- dataset


def test_make_loop_dataset_is_fast_valid_and_consistent():
    t0 = time.perf_counter()
    data = make_loop_dataset(seed=0)
    elapsed = time.perf_counter() - t0
    print(f"make_loop_dataset: {elapsed:.3f} s for {len(data)} scans x {data.n_beams} beams")
    assert isinstance(data, ScanSequence)
    assert data.source == "corridor-loop (simulated)"
    path = loop_path()
    np.testing.assert_array_equal(data.ground_truth, path.poses)
    np.testing.assert_array_equal(data.timestamps, path.timestamps)
    assert np.all(np.diff(data.timestamps) > 0)
    np.testing.assert_array_equal(data.odometry[0], data.ground_truth[0])
    assert data.ranges.shape == (len(path.poses), 181) and data.ranges.dtype == np.float32
    assert not np.any(np.isnan(data.ranges)) and np.all(data.ranges > 0)
    assert np.all(data.ranges[np.isfinite(data.ranges)] < data.max_range)
    assert 0.8 < np.isfinite(data.ranges).mean() < 1.0
    # Finite ranges are the true distances plus 1 cm noise.
    truth = corridor_loop_world().raycast(path.poses[:, :2], path.poses[:, 2:3] + data.angles)
    both = np.isfinite(data.ranges) & np.isfinite(truth)
    assert both.sum() > 0.8 * data.ranges.size
    assert np.abs(data.ranges[both] - truth[both]).max() < 0.06


def test_make_loop_dataset_seeds_and_independent_streams():
    a = make_loop_dataset(seed=3)
    b = make_loop_dataset(seed=3)
    np.testing.assert_array_equal(a.ranges, b.ranges)
    np.testing.assert_array_equal(a.odometry, b.odometry)
    other = make_loop_dataset(seed=4)
    assert not np.array_equal(a.ranges, other.ranges)
    assert not np.array_equal(a.odometry, other.odometry)
    # Odometry settings do not disturb the scans' stream, nor scan settings the odometry's.
    more_drift = make_loop_dataset(seed=3, wheel_base_error=0.05)
    np.testing.assert_array_equal(more_drift.ranges, a.ranges)
    assert not np.array_equal(more_drift.odometry, a.odometry)
    noisier = make_loop_dataset(seed=3, range_noise=0.03, dropout=0.05)
    np.testing.assert_array_equal(noisier.odometry, a.odometry)


def test_make_loop_dataset_full_circle():
    data = make_loop_dataset(seed=0, n_beams=360, fov_deg=360.0)
    assert data.n_beams == 360
    np.testing.assert_allclose(np.diff(data.angles), math.radians(1.0), atol=1e-12)
    assert data.angles[0] == pytest.approx(-math.pi)
    assert data.angles[-1] == pytest.approx(math.pi - math.radians(1.0))
    # With a full circle the laser sees walls all round: nearly every beam has an echo.
    assert np.isfinite(data.ranges).mean() > 0.9
