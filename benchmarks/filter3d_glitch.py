"""The 3D filter's odometry check (rust/src/filter3d.rs, check_odometry3d) against a wheel glitch.

For each world and drive seed the drive is rendered and the rig calibrated from rendered targets
as `benchmarks/filter3d.py` does (its `prepare`; cached under --cache, since rendering the office
takes about two minutes); then, per filter seed, preset tof3d runs with the check off
(`scan_matcher.search_xy` 0) and as shipped, on the drive as recorded ("clean") and with the
wheels glitching once ("glitch": from the scan a fraction AT through the drive on, the odometry is
moved by DX, DY metres and DEG degrees in the robot's frame, as `world_filters.py
--odometry-jump` does for the 2D filter). Errors are the trajectory's mean and final distance to
the truth.

Usage:
    python benchmarks/filter3d_glitch.py --world office --drives 3 4 5 --seeds 0 1 2 \\
        [--odometry-jump 0.5 0.6 0 8] [--particles 30] [--cache results/filter3d_glitch] \\
        [--set SECTION.FIELD=VALUE ...]

Prints one JSON line per run, then a Markdown table for BENCHMARKS.md ("A wheel glitch in the
3D filter").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import pickle
import sys
import time
from datetime import date
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from filter3d import prepare  # noqa: E402  (benchmarks/filter3d.py)
from world_filters import overrides as parse_set  # noqa: E402  (benchmarks/world_filters.py)

from omnitof.eval.trajectory import absolute_trajectory_error  # noqa: E402
from omnitof.geometry import compose, relative  # noqa: E402
from omnitof.slam.config import load_config  # noqa: E402
from omnitof.slam.filter3d import run_slam3d  # noqa: E402


def glitched(scans, at: float, jump: tuple[float, float, float]):
    """`scans` whose odometry jumps by `jump` (x, y in m, heading in degrees, robot frame) at the
    scan a fraction `at` through the drive, and carries the jump on from there."""
    k = min(len(scans) - 1, max(1, int(round(at * len(scans)))))
    before = scans.odometry[k - 1]
    odometry = scans.odometry.copy()
    step = np.array([jump[0], jump[1], math.radians(jump[2])])
    odometry[k:] = compose(compose(before, step), relative(before, scans.odometry[k:]))
    return dataclasses.replace(scans, odometry=odometry), k


def prepared(world: str, drive: int, cache: Path):
    """(scans, integrated frames, their rays) of a rendered, calibrated drive (cached)."""
    path = cache / f"{world}_{drive}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    _, data, _ = prepare(world, drive, "estimated", load_config(preset="tof3d"), None)
    out = (data.scans, data.cloud_frames, data.clouds)
    cache.mkdir(parents=True, exist_ok=True)
    path.write_bytes(pickle.dumps(out))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--drives", type=int, nargs="+", default=[3, 4, 5])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--odometry-jump", nargs=4, type=float, default=[0.5, 0.6, 0.0, 8.0],
                        metavar=("AT", "DX", "DY", "DEG"))
    parser.add_argument("--particles", type=int, default=30)
    parser.add_argument("--cache", type=Path, default=Path("results/filter3d_glitch"))
    parser.add_argument("--set", nargs="*", default=[], metavar="SECTION.FIELD=VALUE",
                        help="over tof3d in every run (e.g. scan_matcher.search_below=0.8, as before "
                        "2026-12-06); the runs without the check still set search_xy 0")
    args = parser.parse_args(argv)
    at, jump = args.odometry_jump[0], tuple(args.odometry_jump[1:])
    print(f"# {date.today()} · {os.cpu_count()} cores · load {os.getloadavg()[0]:.1f} at start")
    print(f"# command: python benchmarks/filter3d_glitch.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    rows = []
    for drive in args.drives:
        scans, frames, clouds = prepared(args.world, drive, args.cache)
        bad, k = glitched(scans, at, jump)
        for seed in args.seeds:
            for inputs, name in ((scans, "clean"), (bad, "glitch")):
                for check in (False, True):
                    overrides = parse_set(args.set)
                    overrides.setdefault("filter", {}).update(seed=seed, particles=args.particles)
                    if not check:
                        overrides.setdefault("scan_matcher", {})["search_xy"] = 0.0
                    cfg = load_config(preset="tof3d", overrides=overrides)
                    start = time.perf_counter()
                    result = run_slam3d(inputs, frames, clouds, cfg).result
                    wall = time.perf_counter() - start
                    err = absolute_trajectory_error(result.trajectory.poses, scans.ground_truth)
                    row = {"world": args.world, "drive": drive, "seed": seed, "input": name,
                           "glitch_at": k if name == "glitch" else None, "check": check,
                           "mean_m": round(err.mean, 3), "final_m": round(err.final, 3),
                           "corrected": result.stats["odometry_corrected_scans"],
                           "s_per_frame": round(result.stats["seconds_per_integrated_frame"]["median"], 4),
                           "wall_s": round(wall, 1)}
                    rows.append(row)
                    print(json.dumps(row), flush=True)
    print("\n| input | runs | mean error m: check off / on | final m: off / on | runs corrected | "
          "runs unchanged | s per frame, median: off / on |")
    print("|---|---|---|---|---|---|---|")
    for name in ("clean", "glitch"):
        pairs = [(a, b) for a in rows for b in rows if a["input"] == b["input"] == name and not a["check"]
                 and b["check"] and (a["drive"], a["seed"]) == (b["drive"], b["seed"])]
        if not pairs:
            continue
        off, on = zip(*pairs)
        same = sum(a["mean_m"] == b["mean_m"] and a["final_m"] == b["final_m"] for a, b in pairs)
        print(f"| {name} | {len(pairs)} | {np.mean([r['mean_m'] for r in off]):.3f} / {np.mean([r['mean_m'] for r in on]):.3f} "
              f"| {np.mean([r['final_m'] for r in off]):.3f} / {np.mean([r['final_m'] for r in on]):.3f} "
              f"| {sum(bool(r['corrected']) for r in on)} | {same} "
              f"| {np.median([r['s_per_frame'] for r in off]):.3f} / {np.median([r['s_per_frame'] for r in on]):.3f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
