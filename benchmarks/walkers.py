"""SLAM on the simulated corridor loop with and without people walking beside the robot.

The Freiburg hospital log, where people walk beside the robot, has no ground truth; this loop
has. Each scenario adds `Walker`s (omnitof.sim.laser2d) to `make_loop_dataset`; the table gives
the absolute trajectory error of the filter's trajectory against the truth.

    python benchmarks/walkers.py --loops 0 1 2 --seeds 0 1 2 --presets laser180-scanmatch sim2d
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.sim.laser2d import Walker, make_loop_dataset
from omnitof.slam.config import load_config, parse_setting, settings_overrides
from omnitof.slam.driver import run_slam

# Seconds into the 160 s loop (0.4 m/s, counter-clockwise from the middle of the bottom
# corridor): 5–40 s is the rest of the bottom corridor, its corner and half the right-hand one;
# 70–110 s most of the top corridor and its corner. Two people keep pace 1.2 and 2 m ahead on the
# robot's left, between it and the inner block's wall (1 m away in the 2 m corridors), as in
# the Freiburg hospital log; "one ahead" walks 1.5 m in front of it for nearly the whole loop.
SCENARIOS = {
    "none": (),
    "two beside": (
        Walker(ahead=1.2, left=0.55, start=5.0, stop=40.0),
        Walker(ahead=2.0, left=0.5, start=5.0, stop=40.0),
        Walker(ahead=1.2, left=0.55, start=70.0, stop=110.0),
        Walker(ahead=2.0, left=0.5, start=70.0, stop=110.0),
    ),
    "one ahead": (Walker(ahead=1.5, left=0.0, start=5.0, stop=150.0),),
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--loops", type=int, nargs="+", default=[0, 1, 2], help="seeds of the simulated loop")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="filter seeds")
    ap.add_argument("--presets", nargs="+", default=["laser180-scanmatch"])
    ap.add_argument("--scenarios", nargs="+", default=list(SCENARIOS), choices=list(SCENARIOS))
    ap.add_argument("--particles", type=int, default=30)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    args = ap.parse_args()

    print("| preset | scenario | loop | filter seeds: mean ATE m | max ATE m | final m | final heading ° | s per run |")
    print("|---|---|---|---|---|---|---|---|")
    for preset in args.presets:
        for scenario in args.scenarios:
            for loop in args.loops:
                scans = make_loop_dataset(seed=loop, walkers=SCENARIOS[scenario])
                rows = []
                for seed in args.seeds:
                    overrides = settings_overrides(dict(parse_setting(t) for t in args.set), "--set")
                    overrides.setdefault("filter", {}).update(particles=args.particles, seed=seed)
                    cfg = load_config(preset=preset, overrides=overrides)
                    start = time.perf_counter()
                    result = run_slam(scans, cfg)
                    seconds = time.perf_counter() - start
                    err = absolute_trajectory_error(result.trajectory.poses, scans.ground_truth)
                    rows.append((err.mean, err.max, err.final, err.heading_final_deg, seconds))
                cols = np.array(rows)
                fmt = lambda k, f: ", ".join(f"{v:{f}}" for v in cols[:, k])  # noqa: E731
                print(f"| {preset} | {scenario} | {loop} | {fmt(0, '.3f')} | {fmt(1, '.3f')} | {fmt(2, '.3f')} | "
                      f"{fmt(3, '.2f')} | {statistics.median(cols[:, 4]):.0f} |", flush=True)


if __name__ == "__main__":
    main()
