"""Gaps in a log without odometry: does the odometry estimated from the scans
(omnitof.slam.scan_odometry) bridge them?

    python benchmarks/scan_odometry_gaps.py LOG RELATIONS [--drop 8] [--places 15] [--faster 1]
    python benchmarks/scan_odometry_gaps.py --simulated

With a log: takes `--places` places where the log's odometry turns fastest (at least 200 scans
apart), cuts `--drop` scans out at each, optionally restamps the scans `--faster` times closer
together (as a faster lidar would send them; the estimate steps per scan, so only its gap rule
sees the rate), estimates the odometry without the log's own, and prints how far the robot
turned in the gaps and the relations error (translational m, rotational deg) of the estimate.

With `--simulated`: the first 32 m of the simulated corridor loop (omnitof.sim.laser2d, seed 0;
one 90° corner over scans 208-234), four stretches of the corner cut in turn, at 10 Hz and
restamped to 40 Hz; prints the mean error to the truth and the final heading error.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings

import numpy as np

from omnitof.eval.relations import evaluate_relations, read_relations
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.geometry import compose, relative, wrap_angle
from omnitof.io.scans import read_scans
from omnitof.slam.config import load_config
from omnitof.slam.scan_odometry import estimate_odometry
from omnitof.types import ScanSequence, Trajectory

SIMULATED_CUTS = [(215, 225), (212, 228), (210, 232), (208, 235)]  # [first cut, first kept after)


def restamped(scans: ScanSequence, faster: float) -> ScanSequence:
    """`scans` with their stamps `faster` times closer together (from the first one)."""
    t = scans.timestamps
    return dataclasses.replace(scans, timestamps=t[0] + (t - t[0]) / faster)


def real_log(log: str, relations: str, drop: int, places: int, faster: float) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the log's own reading notes
        scans = read_scans(log).scans
    heading = scans.odometry[:, 2]
    starts: list[int] = []
    for i in np.argsort(-np.abs(wrap_angle(np.diff(heading)))):
        if len(starts) == places:
            break
        if drop < i < len(scans) - drop and all(abs(i - j) > 200 for j in starts):
            starts.append(int(i) - drop // 2)
    keep = np.ones(len(scans), dtype=bool)
    for a in starts:
        keep[a:a + drop] = False
    cut = scans.take(np.flatnonzero(keep))
    cfg = load_config(preset="laser180-scanmatch")
    t0 = time.perf_counter()
    poses, stats = estimate_odometry(restamped(cut, faster), cfg)
    seconds = time.perf_counter() - t0
    error = evaluate_relations(Trajectory(cut.timestamps, poses), read_relations(relations)).to_dict()
    turned = [np.degrees(abs(wrap_angle(heading[a + drop] - heading[a - 1]))) for a in starts]
    print(f"{log.split('/')[-1]}, {len(starts)} × {drop} scans cut, stamps ×1/{faster:g}: turned in the gaps "
          f"median {np.median(turned):.0f}°, max {max(turned):.0f}°; gaps {stats.gaps}, unmatched {stats.unmatched}, "
          f"{seconds:.1f} s | {error['trans_mean']:.4f} m / {error['rot_mean']:.3f}°")


def simulated() -> None:
    from omnitof.sim.laser2d import make_loop_dataset

    scans = make_loop_dataset(seed=0).slice(0, 320)
    truth = scans.ground_truth
    cfg = load_config(preset="laser180-scanmatch", overrides={"filter": {"particles": 5, "seed": 0}})
    for first, after in SIMULATED_CUTS:
        turn = np.degrees(relative(truth[first - 1], truth[after])[2])
        row = []
        for faster in (1.0, 4.0):
            cut = restamped(scans, faster).take(np.r_[0:first, after:len(scans)])
            poses, stats = estimate_odometry(cut, cfg)
            # The estimate's frame is its own: compared from the truth's first pose.
            error = absolute_trajectory_error(compose(cut.ground_truth[0], relative(poses[0], poses)), cut.ground_truth)
            row.append(f"{10 * faster:g} Hz: gaps {stats.gaps}, {error.mean:.3f} m / {error.heading_final_deg:.2f}°")
        print(f"scans {first}-{after - 1} cut, turned {turn:.0f}° | " + " | ".join(row))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", nargs="?")
    parser.add_argument("relations", nargs="?")
    parser.add_argument("--drop", type=int, default=8)
    parser.add_argument("--places", type=int, default=15)
    parser.add_argument("--faster", type=float, default=1.0)
    parser.add_argument("--simulated", action="store_true")
    args = parser.parse_args()
    if args.simulated:
        simulated()
    elif args.log and args.relations:
        real_log(args.log, args.relations, args.drop, args.places, args.faster)
    else:
        parser.error("give LOG RELATIONS, or --simulated")


if __name__ == "__main__":
    main()
