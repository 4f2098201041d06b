"""The MIT Killian Court log's benchmark relations, put in the times of the ROS bag that carries it.

The benchmark of Kümmerle et al. (Autonomous Robots 27(4), 2009) scores MIT Killian Court with
4677 relations between its CARMEN scans, by their CARMEN times. The CARMEN log itself is not
public in a form we can fetch here, but a ROS bag converted from it is
(INESCTEC/ricoslam, `inesctec_mrdt_slam_2d_datasets/bag/mit-killian.clf2bag.bag`, with the
relations in `.../data/mit-killian.relations`): 17 480 LaserScan and Odometry messages, one per
CARMEN scan in the log's order, whose stamps the converter rewrote to 0.1 s apart. So every
CARMEN time is lost, and a relation names its scans by times the bag does not hold.

This script finds, for each of the relations' 3838 distinct times, the bag's scan index: a
monotone map from times to indices (the scans are in the log's order) chosen by dynamic
programming over
- the wheels: for each relation between two consecutive distinct times (3714 of them, 1.75 s
  apart in the median), the odometry's motion between the two candidate scans against the
  relation's motion (σ 3 cm and 1.5°: the odometry's error over a few scans), and
- the clock: the number of scans between them against the time between them over the log's
  mean scan period (loosely: σ a third of it plus half a scan), which decides where the robot
  stood still and the wheels cannot.
It then writes the relations with the bag's stamps. Written here because no tool re-times a
relations file; the matching is by the odometry, so read its check, not the odometry's fit:

- the odometry against the relations within 5 s (the fit's own residual, for scale: Freiburg 079
  and MIT CSAIL with their true times give 3.4 / 7.7 cm and 0.0 / 7.1 cm median / p90), and
- the scans themselves: for a sample of revisits (relations more than 60 s apart, which the fit
  never saw), the median distance of the later scan's end points, placed by the relation, to the
  earlier scan's. Two scans of a place from other viewpoints share only part of what they see,
  so with their true times ACES gives 6.6 cm (median of 40 revisits; 80 % under 30 cm),
  Freiburg 079 37.5 cm (45 %), MIT CSAIL 67.4 cm (45 %); a scan off by a few scans along the
  path would be off by its motion, 0.1 m a scan.

    python benchmarks/killian_relations.py mit-killian.clf2bag.bag mit-killian.relations \\
        --out mit-killian-bag.relations

sha256: mit-killian.clf2bag.bag 03ed49fe8a7532440d2811bb9f1763684df0a043946c2e4cc8db7be30ee0f223,
mit-killian.relations 0b0f8dfc0746f9dee20b9d6d2a47a805674fd2f5be94f0ba11876bc6e97fab4b.
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from scipy.spatial import cKDTree

from omnitof.errors import OmnitofError
from omnitof.eval.relations import read_relations
from omnitof.geometry import compose, relative, wrap_angle
from omnitof.io.scans import read_scans

SIGMA_XY, SIGMA_DEG = 0.03, 1.5
BAND = 600  # scans either side of the clock's guess that a time may map to


def align(times: np.ndarray, odometry: np.ndarray, pairs: dict[int, np.ndarray]) -> np.ndarray:
    """Scan index of each distinct time (sorted `times`): the monotone map of least cost (module
    docstring). `pairs[k]`: the relation's motion from time k to time k + 1, where there is one."""
    n = len(odometry)
    period = (times[-1] - times[0]) / (n - 1)
    guess = np.round((times - times[0]) / period).astype(int)
    offsets = np.arange(-BAND, BAND + 1)
    cost = np.where((guess[0] + offsets >= 0) & (guess[0] + offsets < n), 0.0, np.inf)
    back = np.zeros((len(times), len(offsets)), dtype=np.int32)
    for k in range(len(times) - 1):
        source = guess[k] + offsets
        new, best = np.full(len(offsets), np.inf), np.zeros(len(offsets), dtype=np.int32)
        # Consecutive distinct times lie 4 scans apart in the median, up to 151 where the
        # relations skip a stretch: the steps tried follow the clock's guess.
        expected = (times[k + 1] - times[k]) / period
        for step in range(max(1, int(0.6 * expected) - 2), int(1.4 * expected) + 5):
            dest = source + step - guess[k + 1] + BAND
            live = np.flatnonzero(np.isfinite(cost) & (dest >= 0) & (dest < len(offsets)) & (source >= 0)
                                  & (source + step < n))
            if not len(live):
                continue
            c = cost[live] + 0.5 * ((step - expected) / (expected / 3 + 0.5)) ** 2
            if k in pairs:
                moved = relative(odometry[source[live]], odometry[source[live] + step])
                d = pairs[k]
                c += 0.5 * (np.hypot(moved[:, 0] - d[0], moved[:, 1] - d[1]) / SIGMA_XY) ** 2
                c += 0.5 * (np.degrees(wrap_angle(moved[:, 2] - d[2])) / SIGMA_DEG) ** 2
            better = c < new[dest[live]]
            new[dest[live][better]] = c[better]
            best[dest[live][better]] = live[better]
        cost, back[k + 1] = new, best
    state = int(np.argmin(cost))
    index = np.zeros(len(times), dtype=int)
    for k in range(len(times) - 1, -1, -1):
        index[k] = guess[k] + offsets[state]
        state = back[k, state]
    return index


def end_points(scans, k: int, pose: np.ndarray) -> np.ndarray:
    """(M, 2) scan k's end points within 30 m, the robot at `pose`."""
    r, a = scans.scan_ranges(k), scans.scan_angles(k)
    ok = np.isfinite(r) & (r < 30.0)
    sensor = compose(pose, scans.sensor_pose)
    return np.column_stack([sensor[0] + r[ok] * np.cos(sensor[2] + a[ok]), sensor[1] + r[ok] * np.sin(sensor[2] + a[ok])])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("bag")
    parser.add_argument("relations")
    parser.add_argument("--out", required=True, help="the relations file to write, in the bag's times")
    parser.add_argument("--check", type=int, default=40, help="revisits whose scans are compared")
    args = parser.parse_args()
    try:
        scans = read_scans(args.bag).scans
        rel = read_relations(args.relations)
    except OmnitofError as err:
        raise SystemExit(f"error: {err}") from None
    times = np.unique(np.concatenate([rel.t1, rel.t2]))
    position = {t: k for k, t in enumerate(times)}
    pairs: dict[int, np.ndarray] = {}
    for a, b, d in zip(rel.t1, rel.t2, rel.delta):
        if position[b] == position[a] + 1:
            pairs[position[a]] = d
    index = align(times, scans.odometry, pairs)
    scan_of = dict(zip(times, index))
    i = np.array([scan_of[t] for t in rel.t1])
    j = np.array([scan_of[t] for t in rel.t2])
    steps = np.diff(index)
    print(f"{len(times)} distinct times -> scans {index[0]}..{index[-1]} of {len(scans)}; "
          f"{len(pairs)} consecutive relations; scans between consecutive times: median {np.median(steps):.0f}, "
          f"max {steps.max()}")

    odometry = relative(scans.odometry[i], scans.odometry[j])
    error = np.hypot(odometry[:, 0] - rel.delta[:, 0], odometry[:, 1] - rel.delta[:, 1])
    near = np.abs(rel.t2 - rel.t1) < 5.0
    print(f"odometry against the relations within 5 s (the fit's residual): median {100 * np.median(error[near]):.1f} cm, "
          f"p90 {100 * np.percentile(error[near], 90):.1f} cm")
    revisits = np.flatnonzero(np.abs(rel.t2 - rel.t1) > 60.0)
    sample = np.random.default_rng(0).choice(revisits, min(args.check, len(revisits)), replace=False)
    gaps = []
    for q in sample:
        earlier = cKDTree(end_points(scans, int(i[q]), np.zeros(3)))
        gaps.append(np.median(earlier.query(end_points(scans, int(j[q]), rel.delta[q]))[0]))
    gaps = np.array(gaps)
    print(f"{len(sample)} revisits (> 60 s apart), the later scan placed by its relation: median distance of its end "
          f"points to the earlier scan's {100 * np.median(gaps):.1f} cm (p90 {100 * np.percentile(gaps, 90):.1f} cm; "
          f"{np.mean(gaps < 0.3):.0%} under 30 cm)")

    stamps = scans.timestamps
    with open(args.out, "w", encoding="utf-8") as out:
        out.write(f"# {args.relations} in the times of {args.bag} (benchmarks/killian_relations.py)\n")
        for a, b, (x, y, yaw) in zip(stamps[i], stamps[j], rel.delta):
            out.write(f"{a:.6f} {b:.6f} {x:.6f} {y:.6f} 0.000000 0.000000 0.000000 {yaw:.6f}\n")
    print(f"written: {args.out} ({len(rel.t1)} relations)")
    if not math.isfinite(float(np.median(gaps))):
        raise SystemExit("no revisit could be checked")


if __name__ == "__main__":
    main()
