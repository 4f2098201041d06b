"""The results folder of a SLAM run, so that a run can be inspected and reproduced:

    map.pgm, map.yaml     the best particle's map (ROS map_server format)
    trajectory.tum        the corrected pose at every scan (TUM: timestamp x y z qx qy qz qw); with
                          the back end, the optimised one
    odometry.tum          the raw odometry at every scan
    ground_truth.tum      the true poses, where the input has them (simulated data)
    config.yaml           the configuration actually used
    map.png               the map with the SLAM and odometry trajectories drawn over it
    pose_graph.png        with the back end: its nodes and loop closures over the map
    pose_graph.g2o        with the back end: its last optimisation's graph (the optimised nodes, the
                          front end's edges and the kept closures) in g2o's text format
    summary.yaml          counts, timings and any evaluation
    map3d.ply, map3d.png  the 3D voxel map of a ToF run, when asked (`write_voxel_outputs`); with
                          the 3D filter, its best particle's (map.pgm is then its projection)
    trajectory_2d.tum     with the 3D filter and --compare-2d: the 2D filter's trajectory

The folder is one unit (`results_folder`): a run builds it under a hidden name beside its
place and renames it into place when it is complete, so the folder is always the complete
result of one run, the previous one or the new one, never a mix of both and never a part of
either. Inside it every file is also written to a temporary name and renamed.
summary.yaml is written last, so a folder that holds it is complete (`is_complete`, which
`omnitof bench` uses to resume an experiment).
"""

from __future__ import annotations

import errno
import os
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from omnitof.errors import OmnitofWarning, OutputError, dump_yaml
from omnitof.interrupts import pause_point
from omnitof.slam.config import SlamConfig
from omnitof.io.atomic import atomic_folder, atomic_write
from omnitof.io.g2o import write_g2o
from omnitof.io.rosmap import write_ros_map
from omnitof.io.tum import write_tum
from omnitof.slam import SlamResult
from omnitof.map3d import VoxelMap
from omnitof.types import Trajectory
from omnitof.viz.maps import plot_map, plot_pose_graph
from omnitof.viz.map3d import height_colors, plot_voxels
from omnitof.io.ply import write_ply

# Every file a run of `omnitof slam` or `omnitof demo` writes into its results folder. A folder
# holding anything else is not replaced: it is not (only) a results folder.
RESULT_FILES = frozenset({
    "map.pgm", "map.yaml", "map.png", "trajectory.tum", "odometry.tum", "ground_truth.tum",
    "config.yaml", "summary.yaml", "pose_graph.png", "pose_graph.g2o", "map3d.ply", "map3d.png", "trajectory_2d.tum",
    # omnitof demo
    "report.md", "overlay.png", "table1.txt", "calibration.yaml", "fig3_amplitude.png",
    "fig3_depth.png", "scan.png", "slice.png",
})  # fmt: skip

# Errors of writing, not of reading: a full disk, a file size limit, a quota.
_WRITE_ERRNOS = {errno.ENOSPC, errno.EFBIG, errno.EDQUOT}


def _only_results(folder: Path) -> None:
    """Refuse to replace a folder that holds anything a run does not write (hidden temporary
    files of an interrupted earlier version of omnitof aside)."""
    foreign = sorted(
        p.name for p in folder.iterdir()
        if p.name not in RESULT_FILES and not (p.name.startswith(".") and p.name.endswith(".tmp"))
    )  # fmt: skip
    if foreign:
        listed = ", ".join(foreign[:3]) + (f" and {len(foreign) - 3} more" if len(foreign) > 3 else "")
        raise OutputError(
            f"{folder}: the folder holds files that are not results of omnitof ({listed}); a run "
            "replaces its results folder as a whole, so give a new or a results folder"
        )


@contextmanager
def results_folder(out: str | Path) -> Iterator[Path]:
    """The results folder `out` as one unit: yields a new, empty folder to write the run's
    files into, which replaces `out` when the block ends without an error
    (omnitof.io.atomic.atomic_folder).

    Checked at once, so that a run that opens its folder first learns of them before any work:
    `out` must be a folder or absent, hold nothing but results of omnitof, and its place must be
    writable (missing parent folders are made). When the block raises (an error, Ctrl-C,
    SIGTERM), `out` is left as it was; a write that fails for lack of room becomes an
    OutputError that says so.
    """
    existed = os.path.isdir(out)  # False for a name the file system cannot hold; atomic_folder says why
    try:
        with atomic_folder(out, may_replace=_only_results) as folder:
            yield folder
    except OSError as err:
        if err.errno not in _WRITE_ERRNOS:
            raise
        left = "the folder was left as it was" if existed else "nothing was written"
        raise OutputError(f"{out}: cannot write the results: {err.strerror}; {left}") from None


def write_results(
    out_dir: str | Path,
    result: SlamResult,
    cfg: SlamConfig,
    *,
    title: str = "",
    ground_truth: np.ndarray | None = None,
    extra: dict[str, Any] | None = None,
) -> dict[str, Path]:
    """Write a run's files into the folder `out_dir` (made if missing); returns the paths
    written, by name. To replace an earlier run's folder as one unit, write into the folder
    that `results_folder` gives."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not result.map.known.any():
        raise OutputError(
            f"{out}: the map is empty: no scan left a mark in it (no beam echoed within "
            "map.max_range, and map.clear_no_echo is off); nothing to write"
        )
    write_ros_map(out / "map.yaml", result.map)
    paths = {
        "map": out / "map.yaml",
        "trajectory": out / "trajectory.tum",
        "odometry": out / "odometry.tum",
        "config": out / "config.yaml",
        "figure": out / "map.png",
        "summary": out / SUMMARY,
    }
    # Poses that share a timestamp share a TUM row (io.tum.write_tum): counted in the summary.
    merged = write_tum(paths["trajectory"], result.trajectory, sort=True)
    if merged:
        warnings.warn(f"trajectory.tum: {merged} of {len(result.trajectory)} poses share their timestamp (to the "
                      "microsecond) with another; a TUM file holds one pose per timestamp, the latest estimate "
                      "(summary.yaml: tum_poses_merged)", OmnitofWarning, stacklevel=2)
    write_tum(paths["odometry"], result.odometry, sort=True)
    pause_point("write")  # half of the files are written (the fault-injection tests stop here)
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
                        result.graph["rejected"], relocalised=result.graph.get("relocalised"),
                        title=f"pose graph: {title}" if title else "")
        if "edges" in result.graph:
            paths["pose_graph_g2o"] = out / "pose_graph.g2o"
            write_g2o(paths["pose_graph_g2o"], result.graph["nodes"], result.graph["edges"],
                      result.graph["measured"], result.graph["information"])
    summary = {"run": result.stats, **(extra or {}), "tum_poses_merged": merged}
    with atomic_write(paths["summary"]) as f:
        dump_yaml(summary, f, sort_keys=False)
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
