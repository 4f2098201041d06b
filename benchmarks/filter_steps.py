"""How the filter's own steps err on a simulated world: each integrated step's motion against the
true one, in the frame of the step's start.

The front end (the preset's filter, back end and final match off, so that nothing repairs it
afterwards) runs on the world_filters cache of a drive; for each pair of consecutive integrated
scans the estimated motion is compared with the true one. The along-track part (median, mean,
90th percentile of its size, largest) says whether the steps lean along the corridors; the
heading part (sum over the run, sum of sizes, largest) says how far the heading walks and by how
much per step. The trajectory's mean and final error to the truth are printed beside them.

    python benchmarks/filter_steps.py --world corridor1 --drive 0 --seeds 0 1 2 \
        [--preset tof-scanmatch] [--set section.field=value ...] [--cache results/world_scans]

Prints one JSON line per seed.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.geometry import relative, wrap_angle
from omnitof.slam import run_slam
from omnitof.slam.config import load_config

sys.path.insert(0, str(Path(__file__).resolve().parent))
from world_filters import extracted_scans, overrides  # noqa: E402


def step_errors(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(K − 1, 3): along (m), across (m) and heading (rad) error of each step's estimated motion
    against the true one, both in the frame of the step's start."""
    est, tru = relative(estimate[:-1], estimate[1:]), relative(truth[:-1], truth[1:])
    d = est - tru
    d[:, 2] = wrap_angle(d[:, 2])
    return d


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="corridor1")
    parser.add_argument("--drive", type=int, default=0)
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--preset", default="tof-scanmatch")
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE")
    parser.add_argument("--tof-errors", default="default", help="as benchmarks/world_filters.py")
    parser.add_argument("--cache", type=Path, default=Path("results/world_scans"))
    args = parser.parse_args(argv)

    scans = extracted_scans(args.world, args.drive, args.cache, args.tof_errors)
    for seed in args.seeds:
        ov = overrides(args.set)
        ov.setdefault("filter", {}).update({"particles": args.particles, "seed": seed, "final_match_passes": 0})
        ov.setdefault("backend", {})["enabled"] = False
        result = run_slam(scans, load_config(preset=args.preset, overrides=ov))
        idx = result.integrated
        e = step_errors(result.trajectory.poses[idx], scans.ground_truth[idx])
        along, heading = 1000 * e[:, 0], np.degrees(e[:, 2])
        ate = absolute_trajectory_error(result.trajectory.poses, scans.ground_truth)
        print(json.dumps({
            "world": args.world, "drive": args.drive, "seed": seed, "preset": args.preset, "set": args.set,
            "steps": len(e),
            "along_median_mm": round(float(np.median(along)), 1), "along_mean_mm": round(float(along.mean()), 1),
            "along_abs_p90_mm": round(float(np.percentile(np.abs(along), 90)), 1),
            "along_max_mm": round(float(np.abs(along).max()), 1),
            "heading_sum_deg": round(float(heading.sum()), 2),
            "heading_abs_sum_deg": round(float(np.abs(heading).sum()), 2),
            "heading_max_deg": round(float(np.abs(heading).max()), 2),
            "mean_error_m": round(ate.mean, 3), "final_error_m": round(ate.final, 3),
        }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
