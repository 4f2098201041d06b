"""Run the paper's 3D variant (sec. V, Fig. 11(b)) of the particle filter over ToF frames.

The filter (rust/src/filter3d.rs, `_core.ParticleFilter3D`) keeps a 3D voxel map per particle
(blocks shared copy-on-write between particles), a planar pose (x, y, θ) drawn from the odometry
motion model or from the 3D scan-matching proposal, and weighs the particles by a 3D likelihood
field on a subsample of each frame's rays (every mirror pixel, through its virtual camera:
`scan.ScanExtractor.rays`). This module feeds it the rays of the frames to integrate (the
keyframes of `driver.select_scans`'s rule, kept while reading: `scan.tof_input`), gives every
scan a pose (the last integrated pose composed with the odometry since), and projects the best
particle's voxels onto the floor as the run's 2D map (map.pgm).

With `backend.enabled` the pose-graph back end (omnitof.slam.backend) runs behind it as behind
the 2D filter: its nodes are the integrated frames, its submaps and loop closures come from the
frames' 2D scans, a correction restarts the particles on voxels rebuilt from every frame's rays
at the optimised poses (`FrontEnd3D`), and the voxel map written at the end is rebuilt the same
way along the final optimised poses.

Clouds: (M, 6) float32 per integrated frame, ray origin on the mirror and end point, robot
frame, metres (`scan.ToFScans.clouds`).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from omnitof import _core
from omnitof.errors import InputError, ResourceError
from omnitof.slam.config import SlamConfig
from omnitof.slam.footprint import clear_footprint
from omnitof.slam.driver import DRIVER_FILTER_FIELDS, DRIVER_MAP_FIELDS, SlamResult, fill_trajectory, in_odometry_frame
from omnitof.slam.anchor import moved, voxel_offset
from omnitof.slam.backend import PoseGraphBackend
from omnitof.slam.limits import MemoryWatch, usable_cores, within_cores
from omnitof.types import OccupancyMap, ScanSequence, Trajectory


class FrontEnd3D:
    """The 3D filter in front of the pose-graph back end (omnitof.slam.backend): the best
    particle's pose and lineage, and, where the graph corrects the newest node, a restart of
    every particle at the corrected pose on a voxel map rebuilt from the integrated frames'
    rays at the nodes' optimised poses (`_core.ParticleFilter3D.reset`)."""

    def __init__(self, pf: "_core.ParticleFilter3D", clouds: dict[int, np.ndarray]):
        self.pf = pf
        self.clouds = clouds  # scan index -> (M, 6) rays of that integrated frame

    def best_pose(self) -> np.ndarray | None:
        return self.pf.best_pose()

    def best_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        return self.pf.best_trajectory()

    def reset_along(self, pose: np.ndarray, scan: int, node_scans: Sequence[int],
                    node_poses: Sequence[np.ndarray]) -> None:
        clouds = [np.ascontiguousarray(self.clouds[int(k)], dtype=np.float32).reshape(-1, 6) for k in node_scans]
        self.pf.reset(np.asarray(pose, dtype=np.float64), int(scan),
                      np.asarray(node_poses, dtype=np.float64).reshape(-1, 3), clouds)


@dataclass
class Slam3DResult:
    """A 3D run: the SlamResult (trajectory at every scan, its map = the projection of the voxel
    map onto the floor, stats) and the best particle's voxel map (`_core.VoxelGrid`)."""

    result: SlamResult
    voxels: Any  # _core.VoxelGrid
    frame_seconds: list[float] = field(default_factory=list)
    offset: np.ndarray = field(default_factory=lambda: np.zeros(2))  # the voxels' world origin (x, y)


def core_sections_3d(cfg: SlamConfig) -> dict:
    """The sections the core's 3D filter takes (every one the 2D filter takes, and filter3d less
    what this driver uses itself)."""
    return cfg.model_dump(
        include={"filter", "motion", "sensor_model", "likelihood_field", "scan_matcher", "map", "filter3d"},
        exclude={"filter": set(DRIVER_FILTER_FIELDS), "map": set(DRIVER_MAP_FIELDS),
                 "filter3d": {"enabled", "pixel_stride"}},
    )


def make_filter3d(cfg: SlamConfig) -> "_core.ParticleFilter3D":
    return _core.ParticleFilter3D(**core_sections_3d(cfg))


def project_to_floor(indices: np.ndarray, log_odds: np.ndarray, resolution: float,
                     z_min: float, z_max: float) -> OccupancyMap:
    """The 2D map of a voxel map: per column (ix, iy), the largest log-odds of its observed
    voxels whose centres lie within [z_min, z_max] m (occupied if any is, free if all are);
    columns with none are unknown."""
    idx = np.asarray(indices, dtype=np.int64).reshape(-1, 3)
    lo = np.asarray(log_odds, dtype=np.float32).reshape(-1)
    zc = (idx[:, 2] + 0.5) * resolution
    sel = (zc >= z_min) & (zc <= z_max)
    idx, lo = idx[sel], lo[sel]
    if len(idx) == 0:
        return OccupancyMap(np.zeros((1, 1), np.float32), np.zeros((1, 1), bool), resolution, (0.0, 0.0))
    ix0, iy0 = idx[:, 0].min(), idx[:, 1].min()
    w, h = int(idx[:, 0].max() - ix0 + 1), int(idx[:, 1].max() - iy0 + 1)
    grid = np.full((h, w), -np.inf, dtype=np.float32)
    np.maximum.at(grid, (idx[:, 1] - iy0, idx[:, 0] - ix0), lo)
    known = np.isfinite(grid)
    return OccupancyMap(np.where(known, grid, 0.0).astype(np.float32), known, resolution,
                        (float(ix0 * resolution), float(iy0 * resolution)))


def run_slam3d(
    scans: ScanSequence,
    frames: Sequence[int],
    clouds: Sequence[np.ndarray],
    cfg: SlamConfig,
    *,
    progress: Callable[[int], None] | None = None,
) -> Slam3DResult:
    """Run the 3D filter over the frames `frames` (indices into `scans`, increasing, the first
    0) with their rays `clouds`; every other scan gets its pose from the odometry.

    Raises:
        InputError: no frames, or frames and clouds that do not pair up.
        ResourceError: memory that ran out.
    """
    cfg = within_cores(cfg)
    frames = np.asarray(frames, dtype=np.int64).reshape(-1)
    if len(frames) == 0 or frames[0] != 0 or len(frames) != len(clouds):
        raise InputError(f"the 3D filter needs the rays of the first frame and one cloud per integrated frame "
                         f"(got {len(frames)} frames, {len(clouds)} clouds)", scans.source or None)
    if np.any(np.diff(frames) <= 0) or frames[-1] >= len(scans):
        raise InputError("the 3D filter's frames must be increasing scan indices", scans.source or None)
    # Odometry far from its origin: the run is moved next to it (omnitof.slam.anchor), and its
    # voxels stay relative to `offset` (omnitof.map3d.voxels notes).
    offset = voxel_offset(scans.odometry[:, :2], cfg.filter3d.resolution)
    try:
        run = _run(moved(scans, offset), frames, clouds, cfg, progress)
    except MemoryError as err:
        raise ResourceError(
            f"out of memory in the 3D filter ({err or 'no detail'}) with filter.particles {cfg.filter.particles} "
            f"and filter3d.resolution {cfg.filter3d.resolution:g} m: choose fewer particles or a coarser resolution"
        ) from None
    run.result, run.offset = in_odometry_frame(run.result, offset, scans), offset
    return run


def _run(scans: ScanSequence, frames: np.ndarray, clouds: Sequence[np.ndarray], cfg: SlamConfig,
         progress: Callable[[int], None] | None) -> Slam3DResult:
    start = time.perf_counter()
    pf = make_filter3d(cfg)
    front = FrontEnd3D(pf, {int(k): c for k, c in zip(frames, clouds)})
    backend = None
    if cfg.backend.enabled:
        backend = PoseGraphBackend(cfg.backend, cfg.map, cfg.likelihood_field.sigma, scans,
                                   cfg.filter.threads or usable_cores())
    prev = scans.odometry[frames[0]]
    seconds: list[float] = []
    cpu_start = time.process_time()
    done = 0
    scored = 0
    corrected_scans: list[int] = []
    memory = MemoryWatch("the 3D filter", f"choose fewer than filter.particles {cfg.filter.particles} or a coarser "
                                          f"filter3d.resolution than {cfg.filter3d.resolution:g} m")
    for step, (k, cloud) in enumerate(zip(frames, clouds), start=1):
        c = np.asarray(cloud, dtype=np.float64).reshape(-1, 6)
        cur = scans.odometry[k]
        t0 = time.perf_counter()
        info = pf.step(prev, cur, np.ascontiguousarray(c[:, :3]), np.ascontiguousarray(c[:, 3:]), int(k))
        scored += info[3]
        if info[4]:
            corrected_scans.append(int(k))
        if backend is not None:
            backend.add_node(int(k), front, bool(info[4]))
        seconds.append(time.perf_counter() - t0)
        prev = cur
        memory.check(step, len(frames))
        if progress is not None:
            progress(int(k) + 1 - done)
            done = int(k) + 1
    cpu = time.process_time() - cpu_start
    if progress is not None and done < len(scans):
        progress(len(scans) - done)
    distinct, refs = pf.block_counts()  # the particles' maps, before a rebuild shares one
    graph = None
    if backend is None:
        corrected = pf.best_trajectory()[1]
    else:
        # The map written is the one along the optimised poses: every frame's rays at its node.
        corrected = backend.finish(front)
        front.reset_along(corrected[-1], int(frames[-1]), frames.tolist(), list(corrected))
        graph = backend.graph(corrected)
    poses = fill_trajectory(scans.odometry, frames, corrected)
    voxels = pf.map()
    indices, log_odds = voxels.observed()
    f3 = cfg.filter3d
    occupancy = project_to_floor(indices, log_odds, voxels.resolution, f3.project_z_min, f3.project_z_max)
    stats = {
        "filter": "3d",
        "scans": len(scans),
        "integrated": int(len(frames)),
        "particles": cfg.filter.particles,
        "resamplings": int(pf.resamplings),
        "proposal": cfg.filter.proposal,
        "scanmatch_fallbacks": int(pf.fallbacks),
        "odometry_corrected_scans": corrected_scans,
        "seconds": time.perf_counter() - start,
        "seconds_per_integrated_frame": {"median": float(np.median(seconds[1:] or seconds)),
                                         "max": float(np.max(seconds))},
        # CPU seconds of every thread of the process per integrated frame: on a shared machine
        # steadier than the wall clock; divided by the cores, what an idle machine would take.
        "cpu_seconds_per_integrated_frame": cpu / len(frames),
        "rays_per_frame": float(np.mean([len(c) for c in clouds])),
        "rays_scored_per_frame": scored / max(1, len(frames) - 1),
        "voxel_blocks_distinct": int(distinct),
        "voxel_blocks_referenced": int(refs),
        "voxel_bytes": int(distinct * _core.ParticleFilter3D.block_bytes()),
        "voxels_observed": int(voxels.voxel_count()),
    }
    if backend is not None:
        stats["backend"] = backend.stats()
        stats["loop_closures"] = backend.closure_table()
        stats["check_corrections"] = backend.correction_table()
    if not occupancy.known.any():
        raise InputError("no ray of any frame left a mark in the 3D map (nothing within filter3d.max_range)",
                         scans.source or None)
    result = SlamResult(
        trajectory=Trajectory(scans.timestamps, poses),
        odometry=Trajectory(scans.timestamps, scans.odometry),
        integrated=frames,
        map=clear_footprint(occupancy, poses, cfg.map.footprint_radius, cfg.map.l_min),
        stats=stats,
        graph=graph,
    )
    return Slam3DResult(result, voxels, seconds)


def trajectory_difference(a: np.ndarray, b: np.ndarray) -> dict:
    """How far two trajectories of the same scans lie apart: mean, median and max position
    difference (m) and mean absolute heading difference (deg)."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    d = np.hypot(a[:, 0] - b[:, 0], a[:, 1] - b[:, 1])
    dth = np.abs(np.remainder(a[:, 2] - b[:, 2] + np.pi, 2 * np.pi) - np.pi)
    return {"mean": float(d.mean()), "median": float(np.median(d)), "max": float(d.max()),
            "heading_mean_deg": float(np.degrees(dth.mean()))}
