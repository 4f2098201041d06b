"""Maps made with the estimated calibration against maps made with the true rig (issue 16).

For each world, the demo's pipeline (`omnitof.demo.run_world`: tof-scanmatch, 200 particles,
seed 0) three times, the same drive, sensor noise and filter seed; only the calibration the
scans are extracted with differs: the true rig, the closed-form estimate (intrinsics, then
mirrors; issue 4), and the jointly refined estimate (the demo's default since issue 16). With
the simulator's systematic distance errors on (issue 15, the demo's default), both estimates
carry the distance correction fitted to walls (`calibration.walls`); the true rig has none,
"true+correction" is the true rig with the same wall fit (the fair reference for the estimates).
Reported: the share of the map's occupied cells within 5 cm of a true wall and the trajectory
errors.

Usage: python benchmarks/calibration_maps.py [--worlds room corridor1 corridor2 office]
    [--kinds true true+correction refined closed] [--out /tmp/calmaps]
"""

from __future__ import annotations

import argparse
from pathlib import Path

from omnitof.demo import DemoSettings, run_world

KINDS = {"true": {"calibrate": False}, "true+correction": {"calibrate": False, "true_rig_correction": True},
         "refined": {"calibrate": True, "refine": True},
         "closed": {"calibrate": True, "refine": False}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["room", "corridor1", "corridor2", "office"])
    parser.add_argument("--kinds", nargs="+", default=["true", "refined", "closed"], choices=list(KINDS))
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("/tmp/calmaps"))
    args = parser.parse_args()
    print("| world | calibration | occupied ≤ 5 cm (%) | SLAM mean (m) | SLAM final (m) | calibration |")
    print("|---|---|---|---|---|---|")
    for world in args.worlds:
        for kind in args.kinds:
            run = run_world(DemoSettings(world=world, seed=args.seed, **KINDS[kind]), args.out / f"{world}-{kind}",
                            progress=False, echo=lambda _: None)
            s = run.summary
            fp = s["evaluation"]["floorplan"]
            traj = s["evaluation"]["trajectory"]["slam"]
            print(f"| {world} | {kind} | {100 * fp['occupied_within_5cm']:.1f} | {traj['mean']:.3f} | "
                  f"{traj['final']:.3f} | {s['calibration'].get('summary', s['calibration'].get('source'))} |",
                  flush=True)


if __name__ == "__main__":
    main()
