"""The results folder of a SLAM run, so that a run can be inspected and reproduced:

    map.pgm, map.yaml     the best particle's map (ROS map_server format)
    trajectory.tum        the corrected pose at every scan (TUM: timestamp x y z qx qy qz qw); with
                          the back end, the optimised one
    odometry.tum          the raw odometry at every scan
    config.yaml           the configuration actually used
    map.png               the map with the SLAM and odometry trajectories drawn over it
    pose_graph.png        with the back end: its nodes and loop closures over the map
    summary.yaml          counts, timings and any evaluation
    map3d.ply, map3d.png  the 3D voxel map of a ToF run, when asked (`write_voxel_outputs`)

Every file is written to a temporary name and renamed, so an interrupted run leaves no
half-written file, and summary.yaml is written last: a folder that holds it is complete
(`is_complete`, which `omnitof bench` uses to resume an experiment).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import yaml

from omnitof.slam.config import SlamConfig
from omnitof.io.atomic import atomic_write
from omnitof.io.rosmap import write_ros_map
from omnitof.io.tum import write_tum
from omnitof.slam import SlamResult
from omnitof.map3d import VoxelMap
from omnitof.types import Trajectory
from omnitof.viz.maps import plot_map, plot_pose_graph
from omnitof.viz.map3d import height_colors, plot_voxels
from omnitof.io.ply import write_ply


def write_results(
    out_dir: str | Path,
    result: SlamResult,
    cfg: SlamConfig,
    *,
    title: str = "",
    ground_truth: np.ndarray | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write the results folder; returns the paths written, by name."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    write_ros_map(out / "map.yaml", result.map)
    paths = {
        "map": out / "map.yaml",
        "trajectory": out / "trajectory.tum",
        "odometry": out / "odometry.tum",
        "config": out / "config.yaml",
        "figure": out / "map.png",
        "summary": out / SUMMARY,
    }
    write_tum(paths["trajectory"], result.trajectory, sort=True)
    write_tum(paths["odometry"], result.odometry, sort=True)
    with atomic_write(paths["config"]) as f:
        f.write(cfg.to_yaml())
    drawn = {"SLAM": result.trajectory.poses, "odometry": result.odometry.poses}
    if ground_truth is not None:
        drawn["ground truth"] = ground_truth
        write_tum(out / "ground_truth.tum", Trajectory(result.trajectory.timestamps, ground_truth), sort=True)
        paths["ground_truth"] = out / "ground_truth.tum"
    plot_map(paths["figure"], result.map, drawn, title=title)
    if result.graph is not None:
        paths["pose_graph"] = out / "pose_graph.png"
        plot_pose_graph(paths["pose_graph"], result.map, result.graph["nodes"], result.graph["closures"],
                        result.graph["rejected"], title=f"pose graph: {title}" if title else "")
    summary = {"run": result.stats, **(extra or {})}
    with atomic_write(paths["summary"]) as f:
        yaml.safe_dump(summary, f, sort_keys=False)
    return paths


SUMMARY = "summary.yaml"


def is_complete(out_dir: str | Path) -> bool:
    """Whether `out_dir` holds a complete run: its summary, the file written last."""
    return (Path(out_dir) / SUMMARY).is_file()


def write_voxel_outputs(vmap: VoxelMap, out_dir: str | Path, *, trajectory: np.ndarray | None = None,
                        title: str = "") -> dict[str, Path]:
    """map3d.ply (occupied voxel centres, coloured by height) and map3d.png in `out_dir`."""
    out = Path(out_dir)
    occupied = vmap.occupied()
    paths = {"map3d_ply": out / "map3d.ply", "map3d_png": out / "map3d.png"}
    write_ply(paths["map3d_ply"], occupied, height_colors(occupied) if len(occupied) else None)
    plot_voxels(paths["map3d_png"], occupied, resolution=vmap.resolution, trajectory=trajectory,
                title=title or "3D occupancy (occupied voxels)")
    return paths
