"""The robot's footprint cleared in the written map (omnitof.slam.footprint, map.footprint_radius)."""

import math

import numpy as np
import pytest

from omnitof.slam import run_slam
from omnitof.slam.config import load_config
from omnitof.slam.footprint import clear_footprint, path_cells
from omnitof.types import OccupancyMap

RES = 0.05
SLACK = RES / math.sqrt(2)  # a path cell's centre lies within this of the path


def _segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = np.clip(((points - a) @ ab) / (ab @ ab), 0.0, 1.0)
    return np.linalg.norm(points - (a + t[:, None] * ab), axis=1)


def _centres(occ: OccupancyMap) -> np.ndarray:
    h, w = occ.log_odds.shape
    rows, cols = np.mgrid[0:h, 0:w]
    return np.stack([occ.origin[0] + (cols + 0.5) * occ.resolution, occ.origin[1] + (rows + 0.5) * occ.resolution], -1)


def _unknown(x0, y0, w, h) -> OccupancyMap:
    return OccupancyMap(np.zeros((h, w), np.float32), np.zeros((h, w), bool), RES, (x0, y0))


def test_the_cells_near_a_drive_become_free_and_no_others():
    occ = _unknown(-1.0, -1.0, 80, 60)
    a, b = np.array([0.0, 0.3]), np.array([2.0, 1.1])
    path = a + np.linspace(0, 1, 37)[:, None] * (b - a)  # poses 5.8 cm apart: more than a cell
    out = clear_footprint(occ, path, 0.3, -2.0)
    assert out.log_odds.shape == occ.log_odds.shape and out.origin == occ.origin
    d = _segment_distance(_centres(out).reshape(-1, 2), a, b).reshape(out.log_odds.shape)
    assert out.known[d <= 0.3 - SLACK].all()
    assert not out.known[d > 0.3 + SLACK].any()
    assert np.all(out.log_odds[out.known] == -2.0)


def test_the_footprint_keeps_what_the_scans_saw_and_grows_the_grid():
    occ = _unknown(0.0, 0.0, 40, 40)
    occ.log_odds[3, 3], occ.known[3, 3] = 1.2, True  # an obstacle at (0.175, 0.175)
    occ.log_odds[3, 5], occ.known[3, 5] = -0.4, True  # seen free once, at (0.275, 0.175)
    out = clear_footprint(occ, np.array([[0.1, 0.1], [0.11, 0.1]]), 0.2, -2.0)
    # The path's cell (2, 2) and a disc of 4 cells: the grid grows by 2 cells below and left.
    assert out.origin == pytest.approx((-0.1, -0.1))
    assert out.log_odds.shape == (42, 42)
    assert out.known[5, 5] and out.log_odds[5, 5] == pytest.approx(1.2)
    assert out.known[5, 7] and out.log_odds[5, 7] == -2.0
    assert out.known[0, 4] and out.log_odds[0, 4] == -2.0  # below the old grid, within 0.2 m
    # Beyond the disc the old grid is as it was.
    np.testing.assert_array_equal(out.known[2 + 10:, 2 + 10:], occ.known[10:, 10:])


def test_a_jump_of_the_pose_is_not_filled_in():
    occ = _unknown(-1.0, -1.0, 100, 40)
    out = clear_footprint(occ, np.array([[0.0, 0.0], [3.0, 0.0]]), 0.2, -2.0)
    centres = _centres(out)
    between = (np.abs(centres[..., 1]) < 0.1) & (centres[..., 0] > 0.5) & (centres[..., 0] < 2.5)
    assert not out.known[between].any()
    assert out.known.sum() == 2 * np.count_nonzero(np.hypot(*np.mgrid[-4:5, -4:5]) * RES <= 0.2 + 1e-9)


def test_radius_zero_and_an_empty_path_leave_the_map_alone():
    occ = _unknown(0.0, 0.0, 10, 10)
    assert clear_footprint(occ, np.zeros((5, 2)), 0.0, -2.0) is occ
    assert clear_footprint(occ, np.full((3, 2), np.nan), 0.3, -2.0) is occ
    assert len(path_cells(np.zeros((0, 2)), RES)) == 0


def test_slam_clears_the_path_and_changes_nothing_the_scans_mapped(corridor_loop):
    scans = corridor_loop.slice(0, 300)
    runs = [run_slam(scans, load_config(preset="sim2d", overrides={"filter": {"particles": 10},
                                                                   "map": {"footprint_radius": r}}))
            for r in (0.0, 0.3)]
    plain, cleared = (r.map for r in runs)
    np.testing.assert_array_equal(runs[0].trajectory.poses, runs[1].trajectory.poses)
    # The first map in the second's grid (the footprint may have grown it).
    dc = round((plain.origin[0] - cleared.origin[0]) / RES)
    dr = round((plain.origin[1] - cleared.origin[1]) / RES)
    h, w = plain.log_odds.shape
    inner = (slice(dr, dr + h), slice(dc, dc + w))
    before_lo, before_known = np.zeros_like(cleared.log_odds), np.zeros_like(cleared.known)
    before_lo[inner], before_known[inner] = plain.log_odds, plain.known
    changed = (cleared.log_odds != before_lo) | (cleared.known != before_known)
    obstacles = plain.known & (plain.log_odds > 0)
    np.testing.assert_array_equal(cleared.log_odds[inner][obstacles], plain.log_odds[obstacles])
    # Every change lies within the footprint, and the footprint is free.
    xy = runs[1].trajectory.poses[:, :2]
    centres = _centres(cleared)
    nearest = np.full(cleared.known.shape, np.inf)
    for a, b in zip(xy[:-1], xy[1:]):
        if np.hypot(*(b - a)) > 1e-9:
            nearest = np.minimum(nearest, _segment_distance(centres.reshape(-1, 2), a, b).reshape(nearest.shape))
    assert changed.any()
    assert (nearest[changed] <= 0.3 + SLACK).all()
    near = nearest <= 0.3 - SLACK
    assert cleared.known[near].all() and (cleared.probability[near] < 0.5).all()
