"""Odometry estimated from the scans, for inputs that have none (omnitof.slam.scan_odometry)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.geometry import compose, relative
from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.slam.scan_odometry import estimate_odometry


@pytest.fixture(scope="module")
def loop_start(corridor_loop):
    return corridor_loop.slice(0, 500)  # 50 m of the simulated loop, two corners


def start_aligned_error(poses, truth):
    """The error of `poses` to `truth` with both started at truth's first pose (an odometry's
    frame is its own)."""
    return absolute_trajectory_error(compose(truth[0], relative(poses[0], poses)), truth)


def cfg(**filter_fields):
    return load_config(preset="laser180-scanmatch", overrides={"filter": {"particles": 5, "seed": 0, **filter_fields}})


def test_scan_odometry_follows_the_simulated_loop_where_the_wheels_drift(loop_start):
    poses, stats = estimate_odometry(loop_start, cfg())
    assert stats.matched == len(loop_start) - 1 and stats.unmatched == 0
    np.testing.assert_array_equal(poses[0], loop_start.odometry[0])  # it starts where the input does
    scans_err = start_aligned_error(poses, loop_start.ground_truth)
    wheels_err = start_aligned_error(loop_start.odometry, loop_start.ground_truth)
    # Over 50 m: 1.9 cm mean and 0.1° at the end, where the simulated wheels err 9.4 cm and 2.5°.
    assert scans_err.mean < 0.05 and scans_err.heading_final_deg < 1.0
    assert wheels_err.mean > 3 * scans_err.mean


def test_a_scan_that_finds_no_map_repeats_the_step_before(loop_start):
    scans = loop_start.slice(0, 40)
    blind = scans.ranges.copy()
    blind[30:] = np.inf  # no echo at all from scan 30 on
    poses, stats = estimate_odometry(dataclasses.replace(scans, ranges=blind), cfg())
    assert stats.unmatched == 10 and stats.matched == 29
    step = relative(poses[28], poses[29])
    for k in range(30, 40):
        np.testing.assert_allclose(relative(poses[k - 1], poses[k]), step, atol=1e-9)


@pytest.mark.parametrize("blind", [1, 3])
def test_blind_first_scans_do_not_hold_the_estimate_still(loop_start, blind):
    # A lidar spinning up sends empty scans first: the failed matches join the map, so the
    # first scan with echoes gives the next ones walls to match.
    ranges = loop_start.ranges.copy()
    ranges[:blind] = np.inf
    scans = dataclasses.replace(loop_start, ranges=ranges).slice(0, 200)
    poses, stats = estimate_odometry(scans, cfg())
    assert stats.unmatched <= blind + 1
    truth = scans.ground_truth
    moved = np.linalg.norm(truth[-1, :2] - truth[0, :2])
    assert moved > 5.0
    # From the first scan with echoes on, as without the blind ones (1.9 cm over these 20 m).
    assert start_aligned_error(poses[blind:], truth[blind:]).mean < 0.05  # 2.0 and 2.7 cm


@pytest.mark.parametrize("rate_hz", [10.0, 40.0])
@pytest.mark.parametrize(("lost", "turned_deg"), [((215, 225), 36), ((212, 228), 55)])
def test_a_gap_in_the_log_during_a_turn_is_bridged(corridor_loop, rate_hz, lost, turned_deg):
    scans = corridor_loop.slice(0, 320)  # 32 m, one corner: a 90° turn over scans 208-234
    # The same scans restamped as a lidar at `rate_hz` would send them (the estimate steps per
    # scan, so only the gap rule sees the rate): at 40 Hz the lost scans are 0.28 and 0.43 s.
    t = scans.timestamps
    scans = dataclasses.replace(scans, timestamps=t[0] + (t - t[0]) * (10.0 / rate_hz))
    truth = scans.ground_truth
    first, after = lost
    # Scans lost in the middle of the turn: the robot turned 36° (or 55°, and went on 0.65 m
    # round the corner) meanwhile, beyond the local climb's reach; the climbs from every heading
    # about the pose before, and about where its motion may have carried it, find it.
    gapped = scans.take(np.r_[0:first, after:320])
    turn = np.degrees(relative(truth[first - 1], truth[after])[2])
    assert turn > turned_deg
    poses, stats = estimate_odometry(gapped, cfg())
    assert stats.gaps == 1 and stats.unmatched == 0
    error = start_aligned_error(poses, gapped.ground_truth)
    assert error.heading_final_deg < 1.0 and error.mean < 0.05  # 0.16-0.18° and 3.3-3.4 cm


def test_jittery_stamps_are_not_gaps(corridor_loop, monkeypatch):
    from omnitof.slam import scan_odometry

    scans = corridor_loop.slice(0, 320)
    truth = scans.ground_truth
    # Scans that come irregularly (as Intel's do; here a tenth of the stamps 0.5 s late, so
    # that intervals of 0.6 s follow 0.1 s steps) are no gaps: the wide search is not run for
    # them. Three median intervals alone would count them.
    rng = np.random.default_rng(0)
    late = 0.5 * (rng.random(len(scans)) < 0.1)
    jittery = dataclasses.replace(scans, timestamps=scans.timestamps + late)
    poses, stats = estimate_odometry(jittery, cfg())
    assert stats.gaps == 0 and stats.unmatched == 0
    assert start_aligned_error(poses, truth).mean < 0.05
    monkeypatch.setattr(scan_odometry, "GAP_QUANTILE", 0.5)
    assert estimate_odometry(jittery.slice(0, 100), cfg())[1].gaps > 5


@pytest.mark.parametrize(("intervals", "expected"), [
    (np.full(1000, 0.025), 0.075),  # a regular lidar at 40 Hz: three intervals
    (np.r_[np.full(900, 0.1), np.full(100, 0.6)], 0.9),  # a tenth of the scans 0.5 s late: 1.5 × 0.6 s
    (np.r_[np.full(900, 0.1), np.full(100, 1.5)], 1.0),  # more irregular still (Intel): at most a second
    (np.r_[np.full(990, 0.2), np.full(10, 5.0)], 0.6),  # a few real gaps do not raise the bar
    (np.zeros(0), np.inf),  # no interval: no gap
])
def test_the_gap_threshold_follows_the_logs_rhythm(intervals, expected):
    from omnitof.slam.scan_odometry import gap_threshold

    assert gap_threshold(intervals) == pytest.approx(expected)


def test_run_slam_estimates_the_odometry_an_input_lacks(loop_start):
    # As `omnitof slam --ignore-odometry` gives it: only the first pose, where the estimate starts.
    first_only = np.broadcast_to(loop_start.odometry[:1], loop_start.odometry.shape)
    unknown = dataclasses.replace(loop_start, odometry=first_only, odometry_known=False)
    result = run_slam(unknown, cfg())
    assert result.stats["scan_odometry"]["matched"] == len(loop_start) - 1
    # The odometry the run reports is the estimate, in the input's frame.
    truth = loop_start.ground_truth
    assert absolute_trajectory_error(result.odometry.poses, truth).mean < 0.05
    # SLAM on it maps the loop as well as SLAM on the wheels (0.113 against 0.121 m here).
    with_wheels = run_slam(loop_start, cfg())
    assert (absolute_trajectory_error(result.trajectory.poses, truth).mean
            < absolute_trajectory_error(with_wheels.trajectory.poses, truth).mean + 0.02)


def test_a_log_with_nothing_to_map_is_refused_before_the_estimate(loop_start, monkeypatch):
    import omnitof.slam.driver as driver
    from omnitof.errors import InputError

    def never(*args, **kwargs):
        raise AssertionError("the odometry was estimated for a log with nothing to map")

    monkeypatch.setattr(driver, "with_scan_odometry", never)
    blind = dataclasses.replace(loop_start, ranges=np.full_like(loop_start.ranges, np.inf), odometry_known=False)
    with pytest.raises(InputError, match="echo"):
        run_slam(blind, cfg())
