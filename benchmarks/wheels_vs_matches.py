"""Which is better on a log, its wheels or its scan matches, judged by the benchmark's relations.

For the relations between scans less than a minute apart, 0.2–1.5 m and less than 10° of turn
apart (one to three integrated steps), the error of the relative motion as three sources give it:

- `wheels`: the log's odometry (the run's `odometry.tum`);
- `run`: the SLAM trajectory (the run's `trajectory.tum`);
- `matcher alone`: for a sample of those pairs, the scan at t2 matched from the odometry's
  prediction in a map of the scans of the `--past` seconds up to t1, placed at the odometry's
  poses, or with `--map-poses run` at the run's (`_core.OccupancyGrid.match_scan`: hill
  climbing and Gauss-Newton on the likelihood field, as the filter's proposal climbs, without
  the filter): what one match can do on this log's scans, whatever the filter makes of it. The
  map is as good as the poses it is built at: read it with the wheels' (or the run's) own
  error beside it.

Medians of |heading error| and |translation error|. Where the wheels beat the matches, the
filter's heading walks by the matcher's noise from step to step (BENCHMARKS.md, issue 13).

    python benchmarks/wheels_vs_matches.py LOG RELATIONS RUN [--pairs 150] [--past 10]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from omnitof import _core
from omnitof.eval.relations import match_times, read_relations, relation_errors
from omnitof.geometry import relative
from omnitof.io.scans import read_scans
from omnitof.io.tum import read_tum
from omnitof.slam.config import load_config

NEARBY_S = 60.0
LENGTH_M = (0.2, 1.5)
TURN_DEG = 10.0
STAMP_TOLERANCE_S = 0.05


def nearest(stamps: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Index of the nearest stamp per query; refuses a query with none within the tolerance."""
    index, ok = match_times(stamps, query, STAMP_TOLERANCE_S)
    if not ok.all():
        raise SystemExit("relations whose stamps match no pose within 0.05 s: is RUN a run of LOG?")
    return index


def errors(poses: np.ndarray, stamps: np.ndarray, rel, which: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    i1, i2 = nearest(stamps, rel.t1[which]), nearest(stamps, rel.t2[which])
    return relation_errors(poses[i1], poses[i2], rel.delta[which])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log")
    parser.add_argument("relations")
    parser.add_argument("run", help="an `omnitof slam` results folder of this log")
    parser.add_argument("--pairs", type=int, default=150, help="pairs matched by the matcher alone")
    parser.add_argument("--past", type=float, default=10.0, help="seconds of scans up to t1 in the map")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sample of pairs")
    parser.add_argument("--map-poses", choices=("wheels", "run"), default="wheels",
                        help="the poses the matcher's map is built at")
    args = parser.parse_args()

    run = Path(args.run)
    cfg = load_config(run / "config.yaml")
    scans = read_scans(args.log).scans
    rel = read_relations(args.relations)
    wheels, slam = read_tum(run / "odometry.tum"), read_tum(run / "trajectory.tum")

    length = np.hypot(rel.delta[:, 0], rel.delta[:, 1])
    turn = np.degrees(np.abs(rel.delta[:, 2]))
    short = np.flatnonzero((rel.t2 - rel.t1 < NEARBY_S) & (length > LENGTH_M[0]) & (length < LENGTH_M[1])
                           & (turn < TURN_DEG))
    if len(short) == 0:
        raise SystemExit(f"{args.relations}: no relation {LENGTH_M[0]}-{LENGTH_M[1]} m long within a minute")

    rows = [("wheels", *errors(wheels.poses, wheels.timestamps, rel, short)),
            ("run", *errors(slam.poses, slam.timestamps, rel, short))]

    rng = np.random.default_rng(args.seed)
    sample = np.sort(rng.choice(short, min(args.pairs, len(short)), replace=False))
    k1, k2 = nearest(scans.timestamps, rel.t1[sample]), nearest(scans.timestamps, rel.t2[sample])
    m, lf = cfg.map, cfg.likelihood_field
    max_range = min(cfg.sensor_model.max_range, scans.max_range)
    at = scans.odometry if args.map_poses == "wheels" else slam.poses[nearest(slam.timestamps, scans.timestamps)]
    found = []
    for a, b in zip(k1, k2):
        grid = _core.OccupancyGrid(m.resolution, m.l_occ, m.l_free, m.l_min, m.l_max)
        for k in np.flatnonzero((scans.timestamps >= scans.timestamps[a] - args.past) & (scans.timestamps <= scans.timestamps[a])):
            grid.integrate(relative(at[a], at[k]), scans.scan_angles(k), scans.scan_ranges(k).astype(np.float32),
                           min(m.max_range, scans.max_range), sensor_pose=scans.sensor_pose)
        pose, _ = grid.match_scan(relative(scans.odometry[a], scans.odometry[b]), scans.scan_angles(b),
                                  scans.scan_ranges(b).astype(np.float32), sensor_pose=scans.sensor_pose,
                                  sigma=lf.sigma, window=lf.window_cells, max_range=max_range)
        found.append(pose)
    whose = {"wheels": "wheels'", "run": "run's"}[args.map_poses]
    rows.append((f"matcher alone (map at the {whose} poses)",
                 *relation_errors(np.zeros((len(sample), 3)), np.array(found), rel.delta[sample])))
    rows.append(("wheels, same pairs", *errors(wheels.poses, wheels.timestamps, rel, sample)))

    print(f"{args.log}, run {args.run}: {len(short)} relations {LENGTH_M[0]}-{LENGTH_M[1]} m and < {TURN_DEG:g}° "
          f"apart within {NEARBY_S:g} s (median length {np.median(length[short]):.2f} m)\n")
    print("| source | pairs | heading error median / 90 % (°) | translation error median / 90 % (cm) |")
    print("|---|---|---|---|")
    for name, trans, rot in rows:
        print(f"| {name} | {len(trans)} | {np.median(rot):.3f} / {np.percentile(rot, 90):.3f} | "
              f"{100 * np.median(trans):.1f} / {100 * np.percentile(trans, 90):.1f} |")


if __name__ == "__main__":
    main()
