"""Scans denser than the map: thinned before the filter (omnitof.slam.thinning), and each map cell
updated once per scan (map.once_per_scan)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from omnitof.eval.floorplan import wall_agreement
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.sim.laser2d import beam_angles, corridor_loop_world, simulate_scans
from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.slam.thinning import DenseScanWarning, thin_dense_scans
from omnitof.types import ScanSequence


def _room_scans(beams: int, scans: int = 3, seed: int = 0) -> ScanSequence:
    """Scans of the corridor loop's world from a few poses, `beams` beams over 360°, remissions
    the beam index (to follow each beam)."""
    world = corridor_loop_world()
    poses = np.array([[1.0 + 0.2 * k, 1.0, 0.1 * k] for k in range(scans)])
    angles = beam_angles(beams, 360.0)
    ranges = simulate_scans(world, poses, angles, max_range=8.0, range_noise=0.0, seed=seed)
    index = np.tile(np.arange(beams, dtype=np.float32), (scans, 1))
    return ScanSequence(timestamps=np.arange(scans, dtype=float), ranges=ranges, angles=angles,
                        odometry=poses, max_range=8.0, remissions=index, source="dense")


def _config(max_beams: int, resolution: float = 0.05):
    return load_config(preset="sim2d", overrides={"map": {"max_beams": max_beams, "resolution": resolution}})


def _cells(angles: np.ndarray, ranges: np.ndarray, cell: float, reach: float) -> set[tuple[int, int]]:
    """End-point cells, one beam at a time (the independent computation)."""
    out = set()
    for a, r in zip(angles, ranges):
        length = min(float(r), reach)
        out.add((math.floor(length * math.cos(a) / cell), math.floor(length * math.sin(a) / cell)))
    return out


def test_scans_within_the_limit_are_left_whole():
    scans = _room_scans(720)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        same, record = thin_dense_scans(scans, _config(720))
    assert same is scans and record is None


def test_always_thins_light_scans_quietly_and_off_leaves_dense_ones():
    light, dense = _room_scans(3600), _room_scans(30_000, scans=1)
    always = load_config(preset="sim2d", overrides={"map": {"thin_beams": "always"}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # asked for: no warning
        thin, record = thin_dense_scans(light, always)
        assert thin_dense_scans(dense, load_config(overrides={"map": {"thin_beams": "off"}})) == (dense, None)
    assert record["rule"] == "always" and record["scans"] == 3
    reach = min(always.map.max_range, light.max_range)
    for i in range(3):  # 3600 beams over 360°: 1.7 cm apart at 1 m, in one 2.5 cm cell each pair
        assert thin.beam_counts[i] == len(_cells(light.angles, light.ranges[i], 0.025, reach)) < 3600


def test_a_dense_scan_keeps_one_beam_of_its_own_per_end_point_cell():
    scans = _room_scans(30_000)
    cfg = _config(30_000 - 1)
    with pytest.warns(DenseScanWarning, match=r"dense: 3 scans have more than map.max_beams 29999 beams"):
        thin, record = thin_dense_scans(scans, cfg)
    assert record["scans"] == 3 and record["median_beams_before"] == 30_000
    reach = min(cfg.map.max_range, scans.max_range)
    for i in range(len(scans)):
        kept = thin.remissions[i, : thin.beam_counts[i]].astype(int)  # the original beam indices
        assert np.all(np.diff(kept) > 0)  # in the scan's own order, none twice
        assert np.array_equal(thin.scan_angles(i), scans.angles[kept])
        assert np.array_equal(thin.scan_ranges(i), scans.ranges[i, kept])
        for group in (np.isfinite, np.isinf):  # echoes and no-echo beams apart
            every = scans.ranges[i][group(scans.ranges[i])], scans.angles[group(scans.ranges[i])]
            mine = thin.scan_ranges(i)[group(thin.scan_ranges(i))], thin.scan_angles(i)[group(thin.scan_ranges(i))]
            assert _cells(mine[1], mine[0], 0.025, reach) == _cells(every[1], every[0], 0.025, reach)
            assert len(mine[0]) == len(_cells(every[1], every[0], 0.025, reach))  # one beam per cell
        assert len(kept) < 30_000 / 3


def test_beyond_the_limit_the_cells_are_kept_evenly():
    scans = _room_scans(30_000, scans=1)
    with pytest.warns(DenseScanWarning, match="and then evenly to 500"):
        thin, record = thin_dense_scans(scans, _config(500))
    assert thin.beam_counts[0] == 500 and record["median_beams_after"] == 500
    gaps = np.diff(np.sort(np.mod(thin.scan_angles(0), 2 * np.pi)))
    assert gaps.max() < 4 * (2 * np.pi / 500)  # spread over the whole turn, not bunched


def test_beams_without_an_echo_do_not_crowd_out_those_with_one():
    # Half the beams read nothing (+inf, NaN, 0): they mark no map (map.clear_no_echo is off),
    # so the budget goes to the echoes first.
    scans = _room_scans(20_000, scans=1)
    ranges = scans.ranges.copy()
    ranges[0, 1::2] = np.array([np.inf, np.nan, 0.0, -1.0], dtype=np.float32)[np.arange(10_000) % 4]
    silent = ScanSequence(timestamps=scans.timestamps, ranges=ranges, angles=scans.angles,
                          odometry=scans.odometry, max_range=8.0)
    cfg = _config(2000)
    echo = np.isfinite(ranges[0]) & (ranges[0] > 0)
    echo_cells = _cells(scans.angles[echo], ranges[0, echo], 0.025, min(cfg.map.max_range, 8.0))
    assert 0 < len(echo_cells) < 2000 < len(_cells(scans.angles, np.where(echo, ranges[0], np.inf), 0.025, 8.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # NaN ranges make no numpy warning
        with pytest.warns(DenseScanWarning, match="a scan has more than map.max_beams 2000"):
            thin, _ = thin_dense_scans(silent, cfg)
    kept = thin.scan_ranges(0)
    echoes = np.isfinite(kept) & (kept > 0)
    assert thin.beam_counts[0] == 2000 and echoes.sum() == len(echo_cells)


def test_light_scans_beside_dense_ones_are_kept_whole():
    dense, light = _room_scans(20_000, scans=1), _room_scans(300, scans=1)
    width = 20_000
    angles = np.full((2, width), np.nan)
    ranges = np.full((2, width), np.inf, dtype=np.float32)
    angles[0], ranges[0] = dense.angles, dense.ranges[0]
    angles[1, :300], ranges[1, :300] = light.angles, light.ranges[0]
    mixed = ScanSequence(timestamps=np.array([0.0, 1.0]), ranges=ranges, angles=angles,
                         odometry=np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0]]), max_range=8.0,
                         beam_counts=np.array([20_000, 300]))
    with pytest.warns(DenseScanWarning, match="a scan has more than"):
        thin, _ = thin_dense_scans(mixed, _config(1000))
    assert thin.beam_counts[0] == 1000
    assert np.array_equal(thin.scan_angles(1), light.angles)
    assert np.array_equal(thin.scan_ranges(1), light.ranges[0])


def test_slam_on_thinned_dense_scans_follows_the_truth_better_than_on_all_beams(corridor_loop):
    # The loop's first 250 scans re-taken with 20 001 beams over 180° at the true poses. Thinned
    # (about 1200 beams left), the filter follows the truth and maps the walls; with every beam
    # it does worse (each wall cell gets hundreds of updates a scan; BENCHMARKS.md, "Scans
    # denser than the map"), and takes five times as long.
    part = corridor_loop.slice(0, 250)
    world = corridor_loop_world()
    angles = beam_angles(20_001, 180.0)
    ranges = simulate_scans(world, part.ground_truth, angles, max_range=8.0, seed=3)
    dense = ScanSequence(timestamps=part.timestamps, ranges=ranges, angles=angles,
                         odometry=part.odometry, max_range=8.0, ground_truth=part.ground_truth)
    runs = {}
    for mode in ("dense", "off"):
        cfg = load_config(preset="sim2d", overrides={"filter": {"particles": 10}, "map": {"thin_beams": mode}})
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            result = run_slam(dense, cfg)
        assert any(isinstance(w.message, DenseScanWarning) for w in caught) == (mode == "dense")
        error = absolute_trajectory_error(result.trajectory.poses, part.ground_truth).mean
        runs[mode] = error, wall_agreement(result.map, world.distance_to_walls, tolerance=0.1).near_fraction
    (error, walls), (error_all, walls_all) = runs["dense"], runs["off"]
    assert error < 0.15 and error < error_all
    assert walls > 0.55 and walls > walls_all


def test_omnitof_slam_says_it_thinned_and_records_it(tmp_path):
    import yaml

    from omnitof.cli import main
    from omnitof.io.carmen import write_carmen

    scans = _room_scans(9000, scans=6)
    log = tmp_path / "dense.clf"
    write_carmen(log, scans)
    out = tmp_path / "run"
    with pytest.warns(DenseScanWarning, match="6 scans have more than map.max_beams 8192 beams .up to 9000.") as caught:
        assert main(["slam", str(log), "--out", str(out), "--particles", "3", "--scan-delay", "0", "--quiet"]) == 0
    assert sum(isinstance(w.message, DenseScanWarning) for w in caught) == 1  # thinned once, said once
    record = yaml.safe_load((out / "summary.yaml").read_text())["input"]["beams_thinned"]
    assert record["rule"] == "dense" and record["scans"] == 6 and record["median_beams_before"] == 9000
    assert record["median_beams_after"] < 9000
    assert yaml.safe_load((out / "config.yaml").read_text())["map"]["thin_beams"] == "dense"  # as asked


def test_once_per_scan_writes_each_cell_of_a_dense_scan_once():
    # Through both bindings that build maps outside the filter (the final map's grid and the back
    # end's submaps): with once_per_scan every known cell holds l_occ or l_free exactly (one
    # update each); per beam, cells near the sensor take one update per beam crossing them.
    from omnitof import _core

    scans = _room_scans(3600, scans=1)

    def grid(once):
        g = _core.OccupancyGrid(0.05, 0.9, -0.4, -20.0, 20.0)
        g.integrate(scans.odometry[0], scans.angles, scans.ranges[0], 8.0, False, None, once_per_scan=once)
        return g.to_dense()[0]

    def submap(once):
        m = _core.Submap(0.05, 0.9, -0.4, -20.0, 20.0, 8.0, once_per_scan=once)
        m.insert(scans.odometry[0], scans.ranges[0], scans.angles)
        return m.to_dense()[0]

    for build in (grid, submap):
        once, per_beam = build(True), build(False)
        known = ~np.isnan(once)
        assert np.array_equal(known, ~np.isnan(per_beam)), build.__name__
        assert np.all(np.isclose(once[known], 0.9) | np.isclose(once[known], -0.4)), build.__name__
        assert per_beam[known].min() < -10 * 0.4, build.__name__  # cells around the sensor, many beams


def test_once_per_scan_runs_with_the_back_end_and_changes_the_map(corridor_loop):
    part = corridor_loop.slice(0, 300)
    runs = {}
    for once in (False, True):
        cfg = load_config(preset="laser180-scanmatch",
                          overrides={"filter": {"particles": 5}, "map": {"once_per_scan": once}})
        assert cfg.backend.enabled
        runs[once] = run_slam(part, cfg)
    assert not np.array_equal(runs[True].map.log_odds, runs[False].map.log_odds)
    for once, run in runs.items():
        error = absolute_trajectory_error(run.trajectory.poses, part.ground_truth).mean
        assert error < 0.3, (once, error)
