"""Maps made with the estimated calibration against maps made with the true rig (issue 16).

For each world, the demo's pipeline (`omnitof.demo.run_world`: tof-scanmatch, 200 particles,
seed 0) three times, the same drive, sensor noise and filter seed; only the calibration the
scans are extracted with differs: the true rig, the closed-form estimate (intrinsics, then
mirrors; issue 4), and the jointly refined estimate (the demo's default since issue 16). With
the simulator's systematic distance errors on (issue 15, the demo's default), both estimates
carry the distance correction fitted to walls (`calibration.walls`); the true rig has none,
"true+correction" is the true rig with the same wall fit (the fair reference for the estimates).
Reported: the share of the map's occupied cells within 5 cm of a true wall and the trajectory
errors; and the same share for a map of every 10th scan at its true pose ("true poses"), which
shows the calibration's effect on the map without the filter's (a filter's path, and so its
map, can change by tens of points with a 0.1 px change of the principal point: BENCHMARKS.md).

With `--no-slam`, only the maps at the true poses (the drive simulated, calibrated, rendered
and its scans extracted; no filter run).

Usage: python benchmarks/calibration_maps.py [--worlds room corridor1 corridor2 office]
    [--kinds true true+correction refined closed] [--seed S] [--no-slam] [--out /tmp/calmaps]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from omnitof.demo import DemoSettings, run_world, simulated_scans, slam_config
from omnitof.eval.floorplan import wall_agreement
from omnitof.sim.laser2d import World2D
from omnitof.slam.driver import dense_to_map
from omnitof.slam.final_match import grid_along

KINDS = {"true": {"calibrate": False}, "true+correction": {"calibrate": False, "true_rig_correction": True},
         "refined": {"calibrate": True, "refine": True},
         "closed": {"calibrate": True, "refine": False}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["room", "corridor1", "corridor2", "office"])
    parser.add_argument("--kinds", nargs="+", default=["true", "refined", "closed"], choices=list(KINDS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/calmaps"))
    parser.add_argument("--no-slam", action="store_true", help="only the maps at the true poses")
    args = parser.parse_args()
    if args.no_slam:
        print("| world | seed | calibration | true poses: occupied ≤ 5 cm (%) |")
        print("|---|---|---|---|")
        for world in args.worlds:
            for kind in args.kinds:
                settings = DemoSettings(world=world, seed=args.seed, **KINDS[kind])
                folder = args.out / f"{world}-{kind}"
                folder.mkdir(parents=True, exist_ok=True)
                sim = simulated_scans(settings, folder)
                share = at_true_poses(sim.data.scans, sim.world, settings.preset)
                print(f"| {world} | {args.seed} | {kind} | {100 * share:.1f} |", flush=True)
        return
    print("| world | calibration | occupied ≤ 5 cm (%) | SLAM mean (m) | SLAM final (m) | true poses: occupied ≤ 5 cm (%) "
          "| calibration |")
    print("|---|---|---|---|---|---|---|")
    for world in args.worlds:
        for kind in args.kinds:
            run = run_world(DemoSettings(world=world, seed=args.seed, **KINDS[kind]), args.out / f"{world}-{kind}",
                            progress=False, echo=lambda _: None)
            s = run.summary
            fp = s["evaluation"]["floorplan"]
            traj = s["evaluation"]["trajectory"]["slam"]
            print(f"| {world} | {kind} | {100 * fp['occupied_within_5cm']:.1f} | {traj['mean']:.3f} | "
                  f"{traj['final']:.3f} | {100 * at_true_poses(run.scans, run.world, run.summary['settings']['preset']):.1f} | "
                  f"{s['calibration'].get('summary', s['calibration'].get('source'))} |", flush=True)


def at_true_poses(scans, world, preset: str) -> float:
    """Share of the occupied cells within 5 cm of a wall in the map of every 10th scan at its
    true pose (the preset's map settings and the floor plan at 0.6 m, as `demo.evaluate_run`)."""
    which = list(range(0, len(scans), 10))
    cfg = slam_config(preset, 0).map
    grid = grid_along(scans, which, scans.ground_truth[which], cfg)
    plan = World2D(world.segments_at(0.6))
    return wall_agreement(dense_to_map(*grid.to_dense(), cfg.resolution), plan.distance_to_walls,
                          tolerance=0.05).near_fraction


if __name__ == "__main__":
    main()
