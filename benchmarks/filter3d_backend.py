"""The pose-graph back end behind the 3D filter (omnitof.slam.backend with omnitof.slam.filter3d).

For each world and drive seed the drive is rendered and the rig calibrated from rendered targets
(`filter3d_glitch.prepared`, cached under --cache); then, per filter seed, preset tof3d runs
without the back end (`backend.enabled: false`) and with it as the preset has it (`--set` adds
settings to the second run).
Errors are the trajectory's mean and final distance to the truth.

Usage:
    python benchmarks/filter3d_backend.py --world office --drives 0 1 2 --seeds 0 1 2 \\
        [--particles 30] [--set backend.min_score=0.6 ...] [--cache results/filter3d_glitch]

Prints one JSON line per run, then a Markdown table for BENCHMARKS.md ("The back end behind the
3D filter").
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from filter3d_glitch import prepared  # noqa: E402  (benchmarks/filter3d_glitch.py)
from world_filters import overrides  # noqa: E402  (benchmarks/world_filters.py: --set items)

from omnitof.eval.trajectory import absolute_trajectory_error  # noqa: E402
from omnitof.slam.config import load_config  # noqa: E402
from omnitof.slam.filter3d import run_slam3d  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--drives", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE",
                        help="settings of the run with the back end (besides backend.enabled)")
    parser.add_argument("--cache", type=Path, default=Path("results/filter3d_glitch"))
    args = parser.parse_args(argv)
    print(f"# {date.today()} · {os.cpu_count()} cores · load {os.getloadavg()[0]:.1f} at start")
    print(f"# command: python benchmarks/filter3d_backend.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    rows = []
    for drive in args.drives:
        scans, frames, clouds = prepared(args.world, drive, args.cache)
        for seed in args.seeds:
            for backend in (False, True):
                ov = {"filter": {"seed": seed, "particles": args.particles}}
                if backend:
                    for section, fields in overrides(args.set).items():
                        ov.setdefault(section, {}).update(fields)
                ov.setdefault("backend", {})["enabled"] = backend
                cfg = load_config(preset="tof3d", overrides=ov)
                start = time.perf_counter()
                result = run_slam3d(scans, frames, clouds, cfg).result
                wall = time.perf_counter() - start
                err = absolute_trajectory_error(result.trajectory.poses, scans.ground_truth)
                stats = result.stats.get("backend") or {}
                row = {"world": args.world, "drive": drive, "seed": seed, "backend": backend,
                       "mean_m": round(err.mean, 3), "final_m": round(err.final, 3),
                       "closures_kept": stats.get("closures_accepted"), "closures_found": stats.get("closures_found"),
                       "feedbacks": stats.get("feedbacks"), "corrected": result.stats["odometry_corrected_scans"],
                       "s_per_frame": round(result.stats["seconds_per_integrated_frame"]["median"], 4),
                       "wall_s": round(wall, 1)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    pairs = [(a, b) for a in rows for b in rows if not a["backend"] and b["backend"]
             and (a["drive"], a["seed"]) == (b["drive"], b["seed"])]
    off, on = zip(*pairs)
    gain = np.array([a["mean_m"] - b["mean_m"] for a, b in pairs])
    print("\n| world (drives) | runs | mean error m: alone / with the back end | paired gain (SE) | better / worse "
          "| final m: alone / with | ends ≤ 5 cm: alone / with | closures kept / found | s per frame, median: alone / with |")
    print("|---|---|---|---|---|---|---|---|---|")
    print(f"| {args.world} ({', '.join(map(str, args.drives))}) | {len(pairs)} "
          f"| {np.mean([r['mean_m'] for r in off]):.3f} / {np.mean([r['mean_m'] for r in on]):.3f} "
          f"| {gain.mean():+.3f} ({gain.std(ddof=1) / np.sqrt(len(gain)) if len(gain) > 1 else 0.0:.3f}) "
          f"| {int((gain > 0).sum())} / {int((gain < 0).sum())} "
          f"| {np.mean([r['final_m'] for r in off]):.3f} / {np.mean([r['final_m'] for r in on]):.3f} "
          f"| {sum(r['final_m'] <= 0.05 for r in off)} / {sum(r['final_m'] <= 0.05 for r in on)} "
          f"| {sum(r['closures_kept'] for r in on)} / {sum(r['closures_found'] for r in on)} "
          f"| {np.median([r['s_per_frame'] for r in off]):.3f} / {np.median([r['s_per_frame'] for r in on]):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
