"""`omnitof demo`: the main job in one command.

Until the omnidirectional ToF simulator, calibration and scan extraction land, the demo drives a
simulated 2D laser around a loop of corridors (omnitof.sim.laser2d) with drifting wheel odometry,
runs the particle filter, scores the trajectory and the map against the simulator's truth, and
writes the results folder (map, trajectories, figure, summary).
"""

from __future__ import annotations

from pathlib import Path

from omnitof.config import load_config
from omnitof.eval.floorplan import wall_agreement
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.results import write_results
from omnitof.sim.laser2d import corridor_loop_world, make_loop_dataset
from omnitof.slam import run_slam


def run_demo(out: str | Path, *, seed: int = 0, particles: int = 30, progress: bool = True) -> dict:
    from tqdm import tqdm

    scans = make_loop_dataset(seed=seed)
    cfg = load_config(preset="sim2d", overrides={"filter": {"particles": particles, "seed": seed}})
    with tqdm(total=len(scans), unit="scan", desc="slam", disable=not progress) as bar:
        result = run_slam(scans, cfg, progress=bar.update)
    world = corridor_loop_world()
    evaluation = {
        "slam_ate": absolute_trajectory_error(result.trajectory.poses, scans.ground_truth).to_dict(),
        "odometry_ate": absolute_trajectory_error(scans.odometry, scans.ground_truth).to_dict(),
        "map_vs_walls": wall_agreement(result.map, world.distance_to_walls).to_dict(),
    }
    paths = write_results(
        out, result, cfg, title="simulated corridor loop", ground_truth=scans.ground_truth,
        extra={"input": {"source": scans.source, "seed": seed}, "evaluation": evaluation},
    )
    s, o, w = evaluation["slam_ate"], evaluation["odometry_ate"], evaluation["map_vs_walls"]
    st = result.stats
    print(
        f"scans {st['scans']} (integrated {st['integrated']}), time {st['seconds']:.1f} s, "
        f"particles {st['particles']}, resamplings {st['resamplings']}"
    )
    print(
        f"trajectory error (mean / final): SLAM {s['mean']:.3f} / {s['final']:.3f} m, "
        f"odometry {o['mean']:.3f} / {o['final']:.3f} m; "
        f"occupied cells within {w['tolerance']:.2f} m of a true wall: {100 * w['near_fraction']:.1f}%"
    )
    print(f"results in {paths['summary'].parent}")
    return evaluation
