"""Odometry estimated from the scans alone (omnitof.slam.scan_odometry) against the logs' own
wheels, both scored by the benchmark relations as a SLAM trajectory would be.

    python benchmarks/scan_odometry.py LOG:RELATIONS [LOG:RELATIONS ...] [--preset laser180-scanmatch]

Prints one line per log: what the estimate did, its time, and the relations error (translational
m, rotational deg; all, and the nearby / revisit split) of the estimate and of the wheels.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings

from omnitof.eval.relations import evaluate_relations, read_relations
from omnitof.io.scans import read_scans
from omnitof.slam.config import load_config
from omnitof.slam.scan_odometry import estimate_odometry
from omnitof.types import Trajectory


def _scored(trajectory: Trajectory, relations) -> str:
    d = evaluate_relations(trajectory, relations).to_dict()
    parts = [f"{d['trans_mean']:.4f} m / {d['rot_mean']:.3f}°"]
    for split in ("nearby", "revisits"):
        if d[split]["trans_mean"] is not None:
            parts.append(f"{split} {d[split]['trans_mean']:.4f} m")
    return ", ".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", metavar="LOG:RELATIONS")
    parser.add_argument("--preset", default="laser180-scanmatch")
    args = parser.parse_args(argv)
    cfg = load_config(preset=args.preset)
    for pair in args.pairs:
        log, _, rel = pair.partition(":")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the readers' notes on the log: not what is measured
            scans = read_scans(log).scans
        relations = read_relations(rel)
        start = time.perf_counter()
        poses, stats = estimate_odometry(scans, cfg)
        seconds = time.perf_counter() - start
        print(f"{log}: {len(scans)} scans, {stats.matched} matched, {stats.unmatched} by the step before, "
              f"{stats.keyframes} keyframes, {stats.gaps} gaps, {seconds:.1f} s | scans: {_scored(Trajectory(scans.timestamps, poses), relations)}"
              f" | wheels: {_scored(Trajectory(scans.timestamps, scans.odometry), relations)}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
