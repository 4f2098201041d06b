"""Where the front end's scan matcher puts a scan that it starts at the true pose, in a map built
from the true poses: the matcher's own error, with no filter, odometry or drift around it.

For a simulated world and drive, every `--every`-th scan is integrated into one occupancy grid
at its true pose (the map settings of `--preset`), and each scan from the fourth on is first
matched against the grid built from the scans before it (hill climbing then Gauss-Newton on the
likelihood field, `OccupancyGrid.match_scan`, the preset's field and step settings, no odometry
prior), started at its true pose. The error of the pose it ends at, in the robot's frame (along
its heading, across it) and in heading, is the matcher's bias where it is consistent and its
scatter where it is not. With `--ideal-scans` the ranges are the exact distances to the floor
plan (benchmarks/world_filters.py), so the sensor plays no part; `--ideal-where-tof` keeps
those exact ranges only in the bins where the ToF scan has a reading (the rig's coverage, no
range error); `--tof-errors` picks the camera errors of the rendered scans as world_filters does,
and `--true-rig` extracts them with the true rig instead of the estimated calibration.
`--complete-map` builds the grid from every n-th scan first (past and future) and then matches
each scan in it: the map is then as complete ahead of the robot as behind it, which SLAM's
map never is. `--lookahead estimated` adds only the next integrated scan, at the pose its own
match in the past map gives: what a front end that decides each scan one step late would have.

    python benchmarks/matcher_bias.py --world corridor1 --drive 0 --every 12 3 [--ideal-scans] \
        [--ideal-where-tof] [--complete-map | --lookahead estimated|true] [--true-rig] [--tof-errors none] \
        [--preset tof-scanmatch] [--cache results/world_scans]

Prints one JSON line per (world, every), then a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path

import numpy as np

from omnitof.geometry import wrap_angle
from omnitof.sim.worlds import load_world
from omnitof.slam.config import load_config
from omnitof.slam.final_match import grid_along

sys.path.insert(0, str(Path(__file__).resolve().parent))
from world_filters import extracted_scans, ideal_scans  # noqa: E402


def matcher_errors(scans, cfg, every: int, complete_map: bool = False, lookahead: str | None = None) -> np.ndarray:
    """(K, 3): along, across (m) and heading (rad) error of each matched scan. With `lookahead`
    ("estimated" or "true"), the next integrated scan is added to the past map before the scan is
    matched in it, at the pose its own match in the past map gives (started at its true pose) or
    at its true pose: the map a fixed-lag front end, which decides a scan once the next is in,
    would match against ("estimated-twice": the next scan matched again with this one's pose
    in the map, and this one again after it)."""
    m, lf, sm = cfg.map, cfg.likelihood_field, cfg.scan_matcher
    max_range = min(cfg.sensor_model.max_range, scans.max_range)
    truth = scans.ground_truth
    every_nth = list(range(0, len(scans), every))
    first = every_nth if complete_map else []  # the complete map holds every scan from the start
    grid = grid_along(scans, first, truth[first].reshape(-1, 3), m)

    def match(g, i):
        return g.match_scan(truth[i], scans.scan_angles(i), scans.scan_ranges(i), sensor_pose=scans.sensor_pose,
                            sigma=lf.sigma, window=lf.window_cells, max_range=max_range, step_xy=sm.step_xy,
                            step_theta=np.radians(sm.step_deg), refinements=sm.refinements,
                            gauss_newton=sm.gauss_newton)[0]

    def past_and(pose, k):  # the past map (true poses) with scan k added at `pose`
        return grid_along(scans, past + [k], np.vstack([truth[past].reshape(-1, 3), pose]), m)

    errors = []
    past: list[int] = []  # the scans in the past map, for the look-ahead's rebuilt grids
    for n, i in enumerate(every_nth):
        nxt = i + every
        if n >= 3:
            if lookahead and nxt < len(scans):
                ahead = truth[nxt] if lookahead == "true" else match(grid, nxt)
                pose = match(past_and(ahead, nxt), i)
                if lookahead == "estimated-twice":  # the next scan posed again with this one in the map
                    ahead = match(past_and(pose, i), nxt)
                    pose = match(past_and(ahead, nxt), i)
            else:
                pose = match(grid, i)
            d = np.asarray(pose) - truth[i]
            c, s = np.cos(truth[i, 2]), np.sin(truth[i, 2])
            errors.append([c * d[0] + s * d[1], -s * d[0] + c * d[1], wrap_angle(d[2])])
        if not complete_map:
            # grid_along's write, one scan at a time: rebuilding the past map at each scan is quadratic.
            grid.integrate(truth[i], scans.scan_angles(i), scans.scan_ranges(i), min(m.max_range, scans.max_range),
                           m.clear_no_echo, scans.sensor_pose)
            past.append(i)
    return np.asarray(errors)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="corridor1")
    parser.add_argument("--drive", type=int, default=0)
    parser.add_argument("--every", nargs="+", type=int, default=[12, 3],
                        help="integrate every n-th scan (12: about the filter's 0.5 m at the demo's speed)")
    parser.add_argument("--preset", default="tof-scanmatch")
    parser.add_argument("--ideal-scans", action="store_true")
    parser.add_argument("--ideal-where-tof", action="store_true",
                        help="exact ranges only in the bins where the ToF scan has a reading")
    parser.add_argument("--complete-map", action="store_true",
                        help="match every scan in the map of all of them (past and future)")
    parser.add_argument("--lookahead", choices=["estimated", "estimated-twice", "true"],
                        help="add the next integrated scan to the past map first, at its own match's pose or its true one")
    parser.add_argument("--tof-errors", default="default", help="as benchmarks/world_filters.py")
    parser.add_argument("--true-rig", action="store_true", help="scans extracted with the true rig")
    parser.add_argument("--cache", type=Path, default=Path("results/world_scans"))
    args = parser.parse_args(argv)
    if args.complete_map and args.lookahead:
        parser.error("--complete-map already holds every scan: --lookahead adds nothing to it")

    world = load_world(args.world)
    scans = extracted_scans(args.world, args.drive, args.cache, args.tof_errors, true_rig=args.true_rig)
    if args.ideal_scans or args.ideal_where_tof:
        exact = ideal_scans(world, scans)
        if args.ideal_where_tof:
            exact = dataclasses.replace(exact, ranges=np.where(np.isfinite(scans.ranges), exact.ranges, np.inf)
                                        .astype(np.float32))
        scans = exact
    kind = ("exact where ToF" if args.ideal_where_tof else "ideal" if args.ideal_scans else
            f"ToF {args.tof_errors}{', true rig' if args.true_rig else ''}")
    cfg = load_config(preset=args.preset)
    rows = []
    for every in args.every:
        e = matcher_errors(scans, cfg, every, args.complete_map, args.lookahead)
        along, across, heading = 1000 * e[:, 0], 1000 * e[:, 1], np.degrees(e[:, 2])
        row = {
            "world": args.world, "drive": args.drive, "every": every, "scans": kind,
            "map": "complete" if args.complete_map else f"past + next ({args.lookahead})" if args.lookahead else "past",
            "matches": len(e),
            "along_mean_mm": round(float(along.mean()), 1), "along_median_mm": round(float(np.median(along)), 1),
            "along_over_1cm": round(float(np.mean(np.abs(along) > 10)), 2),
            "along_over_5cm": round(float(np.mean(np.abs(along) > 50)), 2),
            "across_median_mm": round(float(np.median(across)), 1),
            "across_p90_mm": round(float(np.percentile(np.abs(across), 90)), 1),
            "heading_median_deg": round(float(np.median(heading)), 3),
            "heading_p90_deg": round(float(np.percentile(np.abs(heading), 90)), 3),
        }
        rows.append(row)
        print(json.dumps(row), flush=True)
    print("\n| world | drive | scans | map | every | along mean (median) mm | along > 1 cm / > 5 cm | across median (p90 abs) mm | heading median (p90 abs) ° |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['world']} | {r['drive']} | {r['scans']} | {r['map']} | {r['every']} | "
              f"{r['along_mean_mm']:+.1f} ({r['along_median_mm']:+.1f}) | {r['along_over_1cm']:.2f} / {r['along_over_5cm']:.2f} | "
              f"{r['across_median_mm']:+.1f} ({r['across_p90_mm']:.1f}) | {r['heading_median_deg']:+.3f} ({r['heading_p90_deg']:.3f}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
