"""SLAM on the simulated corridor loop with and without people walking beside the robot.

The Freiburg hospital log, where people walk beside the robot, has no ground truth; this loop
has. Each scenario adds `Walker`s (omnitof.sim.laser2d) to `make_loop_dataset`; the table gives
the absolute trajectory error of the filter's trajectory against the truth. Two worlds: the
tests' narrow loop (2 m corridors, an 8 m laser at 10 Hz) and a wide one nearer the hospital
(3.5 m corridors around a 40 m × 20 m block, a 15 m laser, a scan every 0.2 m). With
`--people-as-no-echo` the people's returns are turned into no echo (the walls they hide stay
hidden): what a perfect filter of moving points would give.

    python benchmarks/walkers.py --world narrow --loops 0 1 2 3 4 --seeds 0 1 2
    python benchmarks/walkers.py --world wide --loops 0 1 2 --seeds 0 1 2 [--people-as-no-echo]
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
from omnitof.types import ScanSequence

WORLDS = {
    "narrow": {},
    "wide": dict(block_width=40.0, block_height=20.0, corridor_width=3.5, max_range=15.0, rate_hz=2.0),
}

# Seconds into each loop (0.4 m/s, counter-clockwise from the middle of the bottom corridor).
# Narrow (160 s): 5–40 s is the rest of the bottom corridor, its corner and half the right-hand
# one; 70–110 s most of the top corridor and its corner. Two people keep pace 1.2 and 2 m ahead
# on the robot's left, between it and the inner block's wall (1 m away), as in the Freiburg
# hospital log; "one ahead" walks 1.5 m in front of it for nearly the whole loop. Wide (350 s):
# three people beside it on its left (the inner wall 1.75 m away) for three minutes of six.
SCENARIOS = {
    "narrow": {
        "none": (),
        "two beside": (
            Walker(ahead=1.2, left=0.55, start=5.0, stop=40.0),
            Walker(ahead=2.0, left=0.5, start=5.0, stop=40.0),
            Walker(ahead=1.2, left=0.55, start=70.0, stop=110.0),
            Walker(ahead=2.0, left=0.5, start=70.0, stop=110.0),
        ),
        "one ahead": (Walker(ahead=1.5, left=0.0, start=5.0, stop=150.0),),
    },
    "wide": {
        "none": (),
        "three beside": tuple(
            Walker(ahead=ahead, left=left, start=t0, stop=t0 + 60.0)
            for t0 in (10.0, 120.0, 230.0)
            for ahead, left in ((1.2, 0.8), (2.0, 0.7), (1.6, 1.3))
        ),
    },
}


def without_people_returns(scans: ScanSequence, plain: ScanSequence) -> ScanSequence:
    """`scans` with every reading that a person made (shorter than the same scan without
    people) turned into no echo."""
    ranges = scans.ranges.copy()
    ranges[np.isfinite(scans.ranges) & ~(scans.ranges >= plain.ranges - 0.05)] = np.inf
    return ScanSequence(timestamps=scans.timestamps, ranges=ranges, angles=scans.angles, odometry=scans.odometry,
                        sensor_pose=scans.sensor_pose, max_range=scans.max_range, ground_truth=scans.ground_truth,
                        source=scans.source, max_range_rule=scans.max_range_rule)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--world", choices=list(WORLDS), default="narrow")
    ap.add_argument("--loops", type=int, nargs="+", default=[0, 1, 2], help="seeds of the simulated loop")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2], help="filter seeds")
    ap.add_argument("--presets", nargs="+", default=["laser180-scanmatch"])
    ap.add_argument("--scenarios", nargs="+", help="default: every scenario of the world")
    ap.add_argument("--people-as-no-echo", action="store_true", help="the people's returns read as no echo")
    ap.add_argument("--particles", type=int, default=30)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE")
    args = ap.parse_args()
    scenarios = SCENARIOS[args.world]
    for name in args.scenarios or []:
        if name not in scenarios:
            ap.error(f"--scenarios: {name!r} is not a scenario of the {args.world} world ({', '.join(scenarios)})")

    print("| world | preset | scenario | loop | filter seeds: mean ATE m | max ATE m | final m | final heading ° | s per run |")
    print("|---|---|---|---|---|---|---|---|---|")
    for preset in args.presets:
        for scenario in args.scenarios or list(scenarios):
            for loop in args.loops:
                scans = make_loop_dataset(seed=loop, walkers=scenarios[scenario], **WORLDS[args.world])
                if args.people_as_no_echo:
                    scans = without_people_returns(scans, make_loop_dataset(seed=loop, **WORLDS[args.world]))
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
                print(f"| {args.world} | {preset} | {scenario}{' (no echo)' if args.people_as_no_echo else ''} | "
                      f"{loop} | {fmt(0, '.3f')} | {fmt(1, '.3f')} | {fmt(2, '.3f')} | {fmt(3, '.2f')} | "
                      f"{statistics.median(cols[:, 4]):.0f} |", flush=True)


if __name__ == "__main__":
    main()
