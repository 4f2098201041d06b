"""The last pass of a run: every scan posed once more in the finished map.

During the run each scan is matched in the map as it was then, which the later scans and the
back end's corrections have since changed; the scans between integrated ones follow their
anchor. Once the run is over the map is final (built from the optimised poses when the back end
runs), so each scan is matched in it once more, by Gauss-Newton on the likelihood field from the
pose the run gave it (within the field's reach by then). A second pass matches in the map
rebuilt from the integrated scans' new poses, and the map written is the one built from the
final poses, so that map and trajectory agree. Every beam counts here (no `beam_stride`): on
Intel, seed 0, the relations error went from 0.0251 m / 0.40° to 0.0191 m / 0.27° after one
pass, 0.0180 m / 0.25° after two; with every second beam, 0.0202 m / 0.30° after one.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from omnitof import _core
from omnitof.slam.config import MapConfig, SlamConfig
from omnitof.types import ScanSequence


def grid_along(scans: ScanSequence, which: Sequence[int], poses: np.ndarray, m: MapConfig) -> _core.OccupancyGrid:
    """A log-odds grid of the scans `which` at `poses` (one row each)."""
    grid = _core.OccupancyGrid(m.resolution, m.l_occ, m.l_free, m.l_min, m.l_max)
    max_range = min(m.max_range, scans.max_range)
    for k, pose in zip(which, poses):
        grid.integrate(pose, scans.scan_angles(int(k)), scans.scan_ranges(int(k)), max_range,
                       m.clear_no_echo, scans.sensor_pose, once_per_scan=m.once_per_scan)
    return grid


def final_match(
    grid: _core.OccupancyGrid, scans: ScanSequence, integrated: np.ndarray, poses: np.ndarray, cfg: SlamConfig
) -> tuple[np.ndarray, _core.OccupancyGrid, int]:
    """`filter.final_match_passes` passes, each re-posing every scan in the map (`grid` first,
    then one rebuilt from the integrated scans' new poses). Returns (poses, the map of the
    integrated scans at their final poses, how many scans kept their pose in the last pass)."""
    stood = 0
    for n in range(cfg.filter.final_match_passes):
        if n > 0:
            grid = grid_along(scans, integrated, poses[integrated], cfg.map)
        poses, stood = _match_all(grid, scans, poses, cfg)
    return poses, grid_along(scans, integrated, poses[integrated], cfg.map), stood


def _match_all(grid: _core.OccupancyGrid, scans: ScanSequence, poses: np.ndarray, cfg: SlamConfig) -> tuple[np.ndarray, int]:
    """Every scan re-posed in `grid` from its row of `poses` (one call into the core, in
    parallel). Where fewer than `scan_matcher.min_matched` of a scan's end points find the map,
    its pose stands. Returns (poses, how many stood)."""
    lf, sensor = cfg.likelihood_field, cfg.sensor_model
    found, share = grid.match_each(
        poses, scans.ranges, scans.angles,
        sensor_pose=scans.sensor_pose, sigma=lf.sigma, z_hit=lf.z_hit, z_rand=lf.z_rand,
        window=lf.window_cells, fit_walls=lf.fit_walls, max_range=min(sensor.max_range, scans.max_range),
        occupied_threshold=cfg.map.occupied_threshold, beam_stride=1,
        gauss_newton=cfg.scan_matcher.gauss_newton, threads=cfg.filter.threads or None,
    )
    stood = share < cfg.scan_matcher.min_matched
    found[stood] = poses[stood]
    return found, int(stood.sum())
