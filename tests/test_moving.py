"""Readings of things that move, dropped before the filter (omnitof.slam.moving), judged against
the simulator's knowledge of which readings the people made."""

from __future__ import annotations

import numpy as np
import pytest

from omnitof.errors import ConfigError
from omnitof.geometry import compose
from omnitof.sim.laser2d import Walker, make_loop_dataset
from omnitof.slam.config import load_config
from omnitof.slam.driver import run_slam
from omnitof.slam.moving import _runs_of_at_least, drop_moving, moving_mask
from omnitof.types import ScanSequence

BESIDE = (Walker(ahead=1.2, left=0.55, start=5.0, stop=40.0), Walker(ahead=2.0, left=0.5, start=5.0, stop=40.0))


def people_readings(walked: ScanSequence, plain: ScanSequence) -> np.ndarray:
    """The readings the people made: shorter than the same beam's without them."""
    return np.isfinite(walked.ranges) & ~(walked.ranges >= plain.ranges - 0.05)


def test_most_readings_of_people_beside_the_robot_go_and_the_walls_stay():
    walked, plain = make_loop_dataset(seed=0, walkers=BESIDE), make_loop_dataset(seed=0)
    people = people_readings(walked, plain)
    mask, kept_whole = moving_mask(walked, lookback=2.0, margin=0.3)
    walls = np.isfinite(walked.ranges) & ~people
    assert (mask & people).sum() > 0.4 * people.sum()
    assert (mask & walls).sum() < 0.002 * walls.sum()
    assert kept_whole == 0
    # Without people, next to nothing goes (the edges of corners that come into view).
    static, _ = moving_mask(plain, lookback=2.0, margin=0.3)
    assert static.sum() < 0.002 * np.isfinite(plain.ranges).sum()


def test_dropped_readings_read_as_no_echo_and_nothing_else_changes():
    walked = make_loop_dataset(seed=1, walkers=BESIDE)
    dropped, info = drop_moving(walked, lookback=2.0, margin=0.3)
    changed = dropped.ranges != walked.ranges
    assert changed.sum() == info.total > 0
    assert np.all(np.isinf(dropped.ranges[changed]))
    np.testing.assert_array_equal(dropped.odometry, walked.odometry)
    np.testing.assert_array_equal(info.dropped, changed.sum(axis=1))


def test_a_wheel_glitch_keeps_the_scans_whole():
    # Odometry that jumps 0.8 m sideways at scan 300 while the robot drove on: against the scans
    # before the jump every wall looks seen through; those scans must be left whole.
    scans = make_loop_dataset(seed=2)
    odometry = scans.odometry.copy()
    odometry[300:] = compose(odometry[300:], np.array([0.0, 0.8, 0.0]))
    glitched = ScanSequence(scans.timestamps, scans.ranges, scans.angles, odometry, max_range=scans.max_range,
                            ground_truth=scans.ground_truth)
    mask, kept_whole = moving_mask(glitched, lookback=2.0, margin=0.3)
    clean, _ = moving_mask(scans, lookback=2.0, margin=0.3)
    assert kept_whole >= 5
    # Scans that lose more than a few readings lose at most the share the guard allows.
    share = mask.sum(axis=1) / np.isfinite(scans.ranges).sum(axis=1)
    assert share.max() <= 0.3
    assert np.array_equal(mask[:300], clean[:300])  # before the jump nothing changes


def test_the_filter_reports_what_it_dropped_and_refuses_clearing_through_people():
    walked = make_loop_dataset(seed=0, walkers=BESIDE).slice(0, 400)
    cfg = load_config(preset="laser180-scanmatch", overrides={"filter": {"moving_lookback": 2.0}, "backend": {"enabled": False}})
    result = run_slam(walked, cfg)
    _, expected = drop_moving(walked, lookback=2.0, margin=0.3)
    assert expected.total > 0
    assert result.stats["moving_readings_dropped"] == expected.total
    assert result.stats["moving_scans_kept_whole"] == expected.scans_kept_whole
    with pytest.raises(ConfigError, match="clear_no_echo"):
        load_config(preset="laser180-scanmatch", overrides={"filter": {"moving_lookback": 2.0}, "map": {"clear_no_echo": True}})


def test_scans_with_their_own_beam_geometry_give_the_same_readings():
    walked = make_loop_dataset(seed=0, walkers=BESIDE).slice(0, 500)
    own = ScanSequence(walked.timestamps, walked.ranges, np.tile(walked.angles, (len(walked), 1)), walked.odometry,
                       max_range=walked.max_range)
    shared, _ = moving_mask(walked, lookback=2.0, margin=0.3)
    per_scan, _ = moving_mask(own, lookback=2.0, margin=0.3)
    assert shared.any()
    np.testing.assert_array_equal(per_scan, shared)


def test_only_runs_of_neighbouring_readings_count():
    flags = np.array([1, 0, 1, 1, 0, 1, 1, 1, 0, 1, 1, 1, 1], dtype=bool)
    expected = np.array([0, 0, 0, 0, 0, 1, 1, 1, 0, 1, 1, 1, 1], dtype=bool)
    np.testing.assert_array_equal(_runs_of_at_least(flags, 3), expected)
    np.testing.assert_array_equal(_runs_of_at_least(np.zeros(5, dtype=bool), 3), np.zeros(5, dtype=bool))
