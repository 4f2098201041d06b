"""Whether a log's per-scan start angles are the ones its laser used: consecutive scans aligned by
ICP from the odometry's motion, the rotation ICP adds, grouped by the two scans' start angles.

A laser in interlaced mode (the Freiburg hospital log's: four quarter-degree offsets) writes a
start angle with every scan. Were a scan labelled with another offset than its own, the scans of
one offset would come out turned against the others by a multiple of a quarter degree, and a
scan matcher would turn the robot with them. Over 0.2 m the wheels' heading errs far less
than that, so the median of ICP's residual rotation per pair of offsets is ~0 where the labels
are right. The ICP is a plain point-to-point one (nearest neighbours from scipy's cKDTree, the
70 % nearest kept, closed-form 2D rotation), written here because only this check needs it.

    python benchmarks/scan_offsets.py ../shared/data/fr-clinic_robotlaser.clf.bz2 [--pairs 1500]
"""

from __future__ import annotations

import argparse
import math

import numpy as np
from scipy.spatial import cKDTree

from omnitof.geometry import relative
from omnitof.io.carmen import read_carmen

MAX_RANGE = 8.0  # m: the readings used
MAX_TURN_DEG = 1.0  # pairs turning more between scans are left out (the odometry's own error grows)


def points(scans, i: int) -> np.ndarray:
    a, r = scans.scan_angles(i), scans.scan_ranges(i)
    ok = np.isfinite(r) & (r < MAX_RANGE)
    return np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])


def icp(fixed: np.ndarray, moving: np.ndarray, pose: np.ndarray, iterations: int = 30) -> np.ndarray:
    """The pose (x, y, θ) of `moving`'s frame in `fixed`'s, refined from `pose`."""
    tree = cKDTree(fixed)
    x = np.asarray(pose, dtype=np.float64).copy()
    for _ in range(iterations):
        c, s = math.cos(x[2]), math.sin(x[2])
        q = moving @ np.array([[c, s], [-s, c]]) + x[:2]
        d, j = tree.query(q)
        keep = d <= np.percentile(d, 70)
        p, f = q[keep], fixed[j[keep]]
        mp, mf = p.mean(axis=0), f.mean(axis=0)
        h = (p - mp).T @ (f - mf)
        turn = math.atan2(h[0, 1] - h[1, 0], h[0, 0] + h[1, 1])
        r = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
        x = np.array([*(r @ x[:2] + mf - r @ mp), x[2] + turn])
    return x


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", help="a CARMEN log whose scans change start angle")
    parser.add_argument("--pairs", type=int, default=1500, help="consecutive pairs to align, spread over the log")
    args = parser.parse_args(argv)
    scans = read_carmen(args.log).scans
    odometry = scans.odometry
    starts = np.round(np.degrees([scans.scan_angles(i)[0] for i in range(len(scans))]), 3)
    turns = np.abs(np.degrees(np.diff(np.unwrap(odometry[:, 2]))))
    candidates = np.flatnonzero(turns < MAX_TURN_DEG) + 1
    chosen = candidates[np.linspace(0, len(candidates) - 1, min(args.pairs, len(candidates))).astype(int)]
    rows = []
    for i in chosen:
        fixed, moving = points(scans, i - 1), points(scans, i)
        if len(fixed) < 50 or len(moving) < 50:
            continue
        wheels = relative(odometry[i - 1], odometry[i])
        rows.append((starts[i - 1], starts[i], math.degrees(icp(fixed, moving, wheels)[2] - wheels[2])))
    rows = np.array(rows)
    print(f"{len(rows)} pairs; start angles {', '.join(f'{a:g}' for a in np.unique(starts))} deg")
    print("| start angle → next (deg) | pairs | ICP's rotation beyond the wheels', median (p25, p75) deg |")
    print("|---|---|---|")
    for first, second in sorted(set(map(tuple, rows[:, :2]))):
        m = (rows[:, 0] == first) & (rows[:, 1] == second)
        r = rows[m, 2]
        print(f"| {first:+.2f} → {second:+.2f} | {m.sum()} | {np.median(r):+.3f} ({np.percentile(r, 25):+.3f}, "
              f"{np.percentile(r, 75):+.3f}) |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
