"""Simulated sequences: the robot's path, its odometry, and the bag `omnitof simulate` writes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnitof.cli import main
from omnitof.geometry import wrap_angle
from omnitof.io.rosbag import read_tof_bag
from omnitof.sim.render import Renderer, RenderSettings
from omnitof.sim.sequence import (
    ROBOT_RADIUS,
    MotionSettings,
    make_sequence,
    render_sequence,
    robot_path,
    sample_poses,
    simulate_bag,
    Sequence,
)
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.laser2d import World2D
from omnitof.sim.worlds import WorldError, load_world, parse_world

WORLDS = ["room", "office", "corridor1", "corridor2"]


@pytest.mark.parametrize("name", WORLDS)
def test_path_is_smooth_at_constant_speed_and_clear_of_obstacles(name):
    world = load_world(name)
    motion = MotionSettings()
    path = robot_path(world, motion)
    steps = np.diff(path.poses, axis=0)
    # Straight steps are exactly speed / rate; on arcs the chord is a hair shorter.
    step_len = np.hypot(steps[:, 0], steps[:, 1])
    assert step_len.max() == pytest.approx(motion.speed / motion.rate_hz, rel=1e-9)
    assert step_len.min() > 0.99 * motion.speed / motion.rate_hz
    turn_rate = np.abs(wrap_angle(steps[:, 2])) * motion.rate_hz
    assert turn_rate.max() <= motion.max_turn_rate * (1 + 1e-9)
    # The heading follows the direction of travel (no sideways slip of a differential drive).
    travel = np.arctan2(steps[:, 1], steps[:, 0])
    assert np.abs(wrap_angle(travel - path.poses[:-1, 2])).max() < motion.max_turn_rate / motion.rate_hz
    clearance = World2D(world.obstacles()).distance_to_walls(path.poses[:, :2])
    assert clearance.min() >= ROBOT_RADIUS


@pytest.mark.parametrize("name", ["corridor1", "corridor2"])
def test_closed_loop_returns_to_start_and_overlaps(name):
    world = load_world(name)
    seq = make_sequence(world, seed=0)
    start = world.waypoints[0]
    # The robot passes the start (a corner of the loop) again near the end, cutting it by the
    # arc of radius speed / max_turn_rate, which passes r(√2 − 1) from a right-angled corner,
    # then drives `overlap` on.
    motion = MotionSettings()
    radius = motion.speed / motion.max_turn_rate
    distances = np.hypot(*(seq.ground_truth[:, :2] - start).T)
    late = distances[len(seq) // 2:]
    assert late.min() == pytest.approx(radius * (math.sqrt(2) - 1), abs=motion.speed / motion.rate_hz)
    assert distances[-1] == pytest.approx(MotionSettings().overlap, abs=0.05)
    assert seq.length == pytest.approx(world.path_length() + MotionSettings().overlap, rel=0.02)
    # Frames at 10 Hz.
    assert np.allclose(np.diff(seq.timestamps), 0.1)


def test_odometry_drifts_visibly_but_starts_true():
    seq = make_sequence(load_world("corridor1"), seed=3)
    assert np.allclose(seq.odometry[0], seq.ground_truth[0])
    drift, turn = seq.odometry_end_error()
    assert drift > 1.0  # raw odometry does not close the 118 m loop
    # ... and the error is mostly systematic: another seed ends in about the same place.
    other = make_sequence(load_world("corridor1"), seed=4)
    assert np.hypot(*(other.odometry[-1, :2] - seq.odometry[-1, :2])) < 0.5 * drift


def test_same_seed_same_sequence_other_seed_other_noise():
    world = load_world("room")
    a, b = make_sequence(world, seed=1), make_sequence(world, seed=1)
    c = make_sequence(world, seed=2)
    assert np.array_equal(a.odometry, b.odometry)
    assert not np.array_equal(a.odometry, c.odometry)
    assert np.array_equal(a.ground_truth, c.ground_truth)


def test_batches_do_not_change_frames():
    world = load_world("room")
    seq = make_sequence(world, seed=5)
    renderer = Renderer(world, settings=RenderSettings(sub_rays=1))
    one = list(render_sequence(seq, renderer, batch=5, stop=5))
    split = list(render_sequence(seq, renderer, batch=2, stop=5))
    for x, y in zip(one, split):
        assert np.array_equal(x.distance, y.distance)
        assert np.array_equal(x.amplitude, y.amplitude)
    # Frames differ in their noise even where the robot has not moved much.
    assert not np.array_equal(one[0].amplitude, one[1].amplitude)


def test_bag_reads_back_with_rig_and_poses(tmp_path):
    world = load_world("room")
    out = tmp_path / "room"
    seq, written = simulate_bag(world, out, seed=7, max_frames=6, samples=True,
                                settings=RenderSettings(sub_rays=1, seed=7))
    assert written == 6
    bag = read_tof_bag(out)
    assert bag.n_frames == 6 and bag.has_samples
    frames = list(bag.frames())
    # The default bag is made with the default systematic errors, and says so in its sidecar.
    assert bag.rig.sensor.errors == ToFErrors.simulation_default() and bag.rig.sensor.errors.motion
    renderer = Renderer(world, sensor=bag.rig.sensor, settings=RenderSettings(sub_rays=1, seed=7))
    direct = list(render_sequence(seq, renderer, stop=6, samples=True))
    for got, want in zip(frames, direct):
        assert got.timestamp == pytest.approx(want.timestamp, abs=1e-9)
        assert np.array_equal(got.distance, want.distance)
        assert np.array_equal(got.samples, want.samples)
        assert np.allclose(got.odometry, want.odometry, atol=1e-9)
        assert np.allclose(got.ground_truth, want.ground_truth, atol=1e-9)
    rig = bag.rig
    assert rig.camera == renderer.camera
    assert np.allclose(rig.robot_T_camera, renderer.robot_T_camera)
    for got_m, want_m in zip(rig.mirrors, renderer.mirrors):
        assert got_m.name == want_m.name
        assert np.allclose(got_m.plane.normal, want_m.plane.normal)
        assert got_m.plane.d == pytest.approx(want_m.plane.d)
        assert np.allclose(got_m.polygon, want_m.polygon)
    assert bag.sidecar["sequence"]["seed"] == 7


def test_path_into_a_wall_is_refused():
    world = parse_world({
        "name": "tight", "ceiling_height": 2.5,
        "walls": [{"points": [[0, 0], [6, 0], [6, 3], [0, 3]], "closed": True},
                  {"points": [[3.0, 1.0], [3.0, 3.0]]}],
        "path": {"waypoints": [[1.0, 0.6], [5.0, 0.6], [5.0, 2.4], [1.0, 2.4]]},
    })
    with pytest.raises(WorldError, match="passes 0.*from an obstacle|too short|clearance"):
        robot_path(world)


def test_odometry_errors_and_a_start_time_that_make_no_odometry_are_refused():
    from omnitof.errors import ConfigError
    from omnitof.sim.sequence import OdometryErrors, make_sequence

    for bad, message in [(dict(heading_drift=math.inf), "odometry.heading_drift must lie within"),
                         (dict(wheel_radius_error=1e300), "odometry.wheel_radius_error must be a fraction"),
                         (dict(alphas=(0.1, math.nan, 0.0, 0.0)), "odometry.alphas must be four finite")]:
        with pytest.raises(ConfigError, match=message):
            OdometryErrors(**bad)  # an infinite drift made every odometry pose NaN
    with pytest.raises(ConfigError, match="start_time must be seconds"):
        make_sequence(load_world("room"), start_time=math.nan)
    with pytest.raises(WorldError, match=r"world 'room': path.waypoints: the path is .* m long: at 0.4 m/s and 1e\+09 Hz "
                       r"that is more than 1e\+07 samples"):
        make_sequence(load_world("room"), motion=MotionSettings(rate_hz=1e9))  # asked numpy for terabytes
    assert len(make_sequence(load_world("room"), motion=MotionSettings(speed=0.005))) > 0  # slow is fine


def test_cli_simulate_writes_a_bag(tmp_path, capsys):
    out = tmp_path / "bag"
    assert main(["simulate", "--world", "room", "--out", str(out), "--max-frames", "3", "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "room: 3 frames" in text
    assert read_tof_bag(out).n_frames == 3
    # A second run does not overwrite silently: one line, status 2.
    assert main(["simulate", "--world", "room", "--out", str(out), "--max-frames", "3", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("omnitof: error:") and len(err.strip().splitlines()) == 1


def test_cli_simulate_unknown_world(tmp_path, capsys):
    assert main(["simulate", "--world", "kitchen", "--out", str(tmp_path / "b"), "--quiet"]) == 2
    assert "kitchen" in capsys.readouterr().err
    assert not (tmp_path / "b").exists()


def test_speed_changes_frame_count():
    world = load_world("corridor2")
    slow = make_sequence(world, motion=MotionSettings(speed=0.3))
    fast = make_sequence(world, motion=MotionSettings(speed=0.5))
    assert len(slow) / len(fast) == pytest.approx(0.5 / 0.3, rel=0.01)
    assert math.isclose(slow.length, fast.length, rel_tol=0.01)


def test_cli_simulate_calibration_renders_target_images(tmp_path, capsys):
    out = tmp_path / "targets"
    assert main(["simulate", "calibration", "--world", "room", "--out", str(out), "--placements", "1",
                 "--boards", "2"]) == 0
    assert len(list((out / "intrinsics").glob("*.png"))) == 2
    assert len(list((out / "mirrors").glob("*.png"))) == 4  # one placement at each of the 4 mirrors
    assert (out / "truth.yaml").exists()
    # Again into the same folder with fewer boards: the folder is replaced whole (the first run's
    # third board stayed beside the second run's truth.yaml), and nothing hidden is left beside it.
    assert main(["simulate", "calibration", "--world", "room", "--out", str(out), "--placements", "1",
                 "--boards", "1"]) == 0
    assert sorted(p.name for p in (out / "intrinsics").iterdir()) == ["board_00.npz", "board_00.png"]
    assert [p.name for p in tmp_path.iterdir()] == ["targets"]
    # A folder of the user's other files is not replaced.
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    capsys.readouterr()
    assert main(["simulate", "calibration", "--out", str(other), "--placements", "1", "--boards", "1"]) != 0
    assert "not calibration target images" in capsys.readouterr().err
    assert [p.name for p in other.iterdir()] == ["notes.txt"]


def test_sample_poses_follow_a_steady_turn_inside_and_at_the_ends():
    # Driving an arc at constant speed and turn rate: the pose at any time is known exactly,
    # and linear interpolation between frames of a steady turn is exact in θ; x and y are
    # compared with the chord, the linear interpolation's own error (< 1 mm here).
    world = load_world("room")
    t = np.arange(6) * 0.1
    omega, speed = 0.6, 0.4
    truth = np.column_stack([speed * t, np.zeros_like(t), wrap_angle(omega * t + 3.0)])
    seq = Sequence(world=world, timestamps=100.0 + t, ground_truth=truth, odometry=truth, length=1.0)
    got = sample_poses(seq, range(6), 0.005)
    offsets = (np.arange(4) - 1.5) * 0.005
    np.testing.assert_allclose(wrap_angle(got[..., 2] - (omega * (t[:, None] + offsets) + 3.0)), 0.0, atol=1e-12)
    np.testing.assert_allclose(got[..., 0], speed * (t[:, None] + offsets), atol=1e-12)


@pytest.mark.parametrize("world, speed, message", [
    ("room", 0.8, "leg 1 (1.50 m) is too short for its corner arcs; at 0.8 m/s the corners are arcs of 1.33 m radius"),
    ("corridor1", 1.0, "from an obstacle at (4.93, 21.03); it needs 0.3 m (move path.waypoints); at 1 m/s the "
                       "corners are arcs of 1.67 m radius"),
])
def test_a_speed_a_bundled_world_cannot_be_driven_at_is_named(world, speed, message):
    """The corners' arcs are speed / the largest turn rate: a bundled world refused at a higher
    speed blamed its own waypoints, which a user cannot edit. The message names the speed."""
    from omnitof.sim.worlds import WorldError, load_world

    with pytest.raises(WorldError) as err:
        robot_path(load_world(world), MotionSettings(speed=speed))
    assert message in str(err.value) and "a lower speed turns tighter" in str(err.value)
    robot_path(load_world(world), MotionSettings())  # the default speed drives it
