"""The scan-matching proposal and the likelihood field (issue: beyond the paper's filter)."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof import _core
from omnitof.slam.config import load_config
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.geometry import wrap_angle
from omnitof.slam import run_slam
from omnitof.types import ScanSequence


def map_from_truth(scans, stop):
    grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
    for k in range(0, stop, 8):
        grid.integrate(scans.ground_truth[k], scans.angles, scans.ranges[k], scans.max_range)
    return grid


@pytest.mark.parametrize("k", [120, 400, 700])
def test_matcher_recovers_a_displaced_pose(corridor_loop, k):
    # Map from the true poses of the scans before k; scan k matched from 8 cm and 3° off.
    grid = map_from_truth(corridor_loop, k)
    truth = corridor_loop.ground_truth[k]
    start = truth + np.array([0.06, -0.05, np.radians(3.0)])
    pose, mean_ll = grid.match_scan(start, corridor_loop.angles, corridor_loop.ranges[k],
                                    max_range=corridor_loop.max_range, sigma=0.03)
    err = np.asarray(pose) - truth
    assert np.hypot(err[0], err[1]) < 0.03
    assert abs(np.degrees(wrap_angle(err[2]))) < 0.5
    assert mean_ll > 0.0  # most end points sit on walls (density above 1/m)


def test_matcher_takes_a_far_start_without_panicking_and_refuses_a_non_finite_one():
    # A start a billion kilometres out finds no obstacle (its score is the floor of the field's
    # log-likelihood, ln(z_rand / max_range) per beam) and stays put; a NaN start is a ValueError.
    angles = np.linspace(-np.pi, np.pi, 90, endpoint=False)
    ranges = np.full(90, 2.0, np.float32)
    grid = _core.OccupancyGrid(0.05, 0.9, -0.4, -2.0, 3.5)
    grid.integrate(np.zeros(3), angles, ranges, 10.0)
    pose, mean_ll = grid.match_scan(np.array([1e12, 0.0, 0.0]), angles, ranges, max_range=10.0)
    assert pose[0] == 1e12
    assert mean_ll == pytest.approx(np.log(0.1 / 10.0))
    with pytest.raises(ValueError, match="finite"):
        grid.match_scan(np.array([np.nan, 0.0, 0.0]), angles, ranges, max_range=10.0)


def test_likelihood_field_observation_model_closes_the_loop(corridor_loop):
    # The odometry proposal weighed with the likelihood field instead of the beam model. The
    # field's log-likelihood spans a wider range than the beam model's, so it is tempered harder.
    cfg = load_config(preset="sim2d", overrides={
        "filter": {"particles": 100},
        "sensor_model": {"model": "likelihood_field", "effective_beams": 3.0},
        # The nearest mean end point, as tuned for this test (sim2d fits walls for the scan matcher).
        "likelihood_field": {"sigma": 0.1, "fit_walls": False},
    })
    result = run_slam(corridor_loop, cfg)
    slam = absolute_trajectory_error(result.trajectory.poses, corridor_loop.ground_truth)
    odom = absolute_trajectory_error(corridor_loop.odometry, corridor_loop.ground_truth)
    assert slam.final < 0.2 < 0.8 < odom.final
    assert slam.mean < 0.5 * odom.mean


def scanmatch_config(**filter_overrides):
    return load_config(preset="sim2d", overrides={
        "filter": {"proposal": "scanmatch", "particles": 10, **filter_overrides},
        "scan_matcher": {"odometry_prior": True},
    })


def test_scanmatch_proposal_beats_raw_odometry(corridor_loop):
    result = run_slam(corridor_loop, scanmatch_config())
    slam = absolute_trajectory_error(result.trajectory.poses, corridor_loop.ground_truth)
    odom = absolute_trajectory_error(corridor_loop.odometry, corridor_loop.ground_truth)
    assert result.stats["scanmatch_fallbacks"] == 0
    assert slam.mean < 0.5 * odom.mean
    assert slam.final < 0.5 * odom.final


def test_scanmatch_is_identical_for_one_and_two_threads(corridor_loop):
    scans = corridor_loop.slice(0, 400)
    one = run_slam(scans, scanmatch_config(threads=1, seed=5))
    two = run_slam(scans, scanmatch_config(threads=2, seed=5))
    assert np.array_equal(one.map.log_odds, two.map.log_odds)
    assert np.array_equal(one.trajectory.poses, two.trajectory.poses)


def test_failed_matches_fall_back_to_odometry_and_are_counted(corridor_loop):
    # After scan 200 the sensor sees nothing: no end point can match, every particle of every
    # later step must fall back to the odometry proposal.
    scans = corridor_loop.slice(0, 400)
    ranges = scans.ranges.copy()
    ranges[200:] = np.inf
    blind = ScanSequence(scans.timestamps, ranges, scans.angles, scans.odometry, max_range=scans.max_range)
    result = run_slam(blind, scanmatch_config())
    later = int(np.sum(result.integrated >= 200))
    assert later > 5
    assert result.stats["scanmatch_fallbacks"] == 10 * later


@pytest.mark.parametrize("seed", [0, 1])
def test_scanmatch_10_particles_beats_odometry_100(seed):
    # Issue 6's target: on the corridor loop (180° laser looking forward, odometry with 1 % distance
    # and 1.5 % turn errors) the scan-matching proposal with 10 particles tracks the truth better
    # than the odometry proposal with 100. It takes a matcher that holds heading and distance in
    # the corridors (preset sim2d): end points scored by their distance to the wall fitted through
    # the mean end points nearby, not to the nearest one (likelihood_field.fit_walls, see
    # scan_match.rs), with a 2 cm field, and a proposal Gaussian that adds little noise.
    from omnitof.sim.laser2d import make_loop_dataset

    scans = make_loop_dataset(seed=seed)
    odo = run_slam(scans, load_config(preset="sim2d", overrides={"filter": {"particles": 100}}))
    sm = run_slam(scans, load_config(preset="sim2d", overrides={"filter": {"particles": 10, "proposal": "scanmatch"}}))
    odo_ate = absolute_trajectory_error(odo.trajectory.poses, scans.ground_truth).mean
    sm_ate = absolute_trajectory_error(sm.trajectory.poses, scans.ground_truth).mean
    assert sm.stats["scanmatch_fallbacks"] == 0
    assert sm_ate < odo_ate, (sm_ate, odo_ate)


def with_odometry_jump(scans, at, jump):
    """The odometry from scan `at` on shifted by `jump` (x, y, θ in the robot frame of scan at−1):
    wheels that spun or slid while the robot stayed put."""
    from omnitof.geometry import compose, relative

    before = scans.odometry[at - 1]
    odometry = scans.odometry.copy()
    odometry[at:] = compose(compose(before, np.asarray(jump)), relative(before, scans.odometry[at:]))
    return ScanSequence(scans.timestamps, scans.ranges, scans.angles, odometry,
                        max_range=scans.max_range, ground_truth=scans.ground_truth)


@pytest.mark.parametrize("distinct", [0.0, 0.2])
def test_wide_search_catches_an_odometry_jump(corridor_loop, distinct):
    # 0.6 m and 8° of odometry that never happened, well beyond the reach of the hill climbing
    # (a few cells), as the robot drives towards the end of a corridor (scan 150): without the
    # wide search every particle is matched in the wrong place and the map ahead is drawn 0.6 m
    # off; with it, the one step is corrected and named. (Along a bare corridor no matcher
    # could see such a jump: the search only runs when the local match leaves much of the scan
    # off the map.) With tof-scanmatch's `search_distinct` 0.2 too: the end wall in view makes
    # the right pose stand out (measured: between 0.2 and 0.4 here).
    scans = with_odometry_jump(corridor_loop.slice(0, 500), 150, [0.6, 0.0, np.radians(8.0)])
    plain = scanmatch_config()
    searching = scanmatch_config()
    searching.scan_matcher.search_xy = 1.0
    searching.scan_matcher.search_distinct = distinct
    before = run_slam(scans, plain)
    after = run_slam(scans, searching)
    late = slice(160, None)
    err_before = absolute_trajectory_error(before.trajectory.poses[late], scans.ground_truth[late])
    err_after = absolute_trajectory_error(after.trajectory.poses[late], scans.ground_truth[late])
    assert err_before.mean > 0.3
    assert err_after.mean < 0.1
    first_after_jump = int(after.integrated[np.searchsorted(after.integrated, 150)])
    assert after.stats["odometry_corrected_scans"] == [first_after_jump]
    assert before.stats["odometry_corrected_scans"] == []


@pytest.mark.parametrize("drive", [2, 3])
def test_wide_search_waits_for_a_map_of_more_than_one_scan(drive):
    # The office's first frames see two short stretches of far walls (about ten readings); the
    # second integrated frame sees the next stretch of the same walls, "unexplained" there for
    # want of map, not for wrong wheels, and the wide search used to fit its ten end points onto
    # the stretches already mapped: a 0.3 m jump at scan 13 (drive seeds 2 and 3) that the whole
    # run kept. The check now starts at the third integrated scan (rust/src/filter.rs,
    # CHECK_FROM_STEP); a real glitch later on is still caught (above).
    from omnitof.scan.extract import ScanExtractor
    from omnitof.scan.tof_input import tof_scans
    from omnitof.sim.render import Renderer, RenderSettings
    from omnitof.sim.sequence import make_sequence, render_sequence
    from omnitof.sim.worlds import load_world

    world = load_world("office")
    renderer = Renderer(world, settings=RenderSettings(seed=drive, sub_rays=1))
    data = tof_scans(render_sequence(make_sequence(world, seed=drive), renderer, stop=40),
                     ScanExtractor.from_rig(renderer.rig))
    run = run_slam(data.scans, load_config(preset="tof-scanmatch"))
    assert run.stats["odometry_corrected_scans"] == []
    err = np.hypot(*(run.trajectory.poses[:, :2] - data.scans.ground_truth[:, :2]).T)
    assert err.max() < 0.1, err.max()  # measured 0.04 / 0.02 m (0.31 / 0.30 m with the jump)


@pytest.mark.parametrize("gate, value", [("search_distinct", 0.6), ("search_min_points", 10_000)])
def test_wide_search_keeps_the_odometry_where_its_gate_says_so(corridor_loop, gate, value):
    # The same jump, with `search_distinct` above what the right pose scores over the rest of the
    # window, or `search_min_points` above the end points any scan holds (the Rust tests show why
    # a scan of one reading must not be searched): the search's pose is not taken, and the run is
    # the one without the search.
    scans = with_odometry_jump(corridor_loop.slice(0, 500), 150, [0.6, 0.0, np.radians(8.0)])
    strict = scanmatch_config()
    strict.scan_matcher.search_xy = 1.0
    setattr(strict.scan_matcher, gate, value)
    kept = run_slam(scans, strict)
    plain = run_slam(scans, scanmatch_config())
    assert kept.stats["odometry_corrected_scans"] == []
    np.testing.assert_array_equal(kept.trajectory.poses, plain.trajectory.poses)
