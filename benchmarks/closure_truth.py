"""How high a *correct* loop closure scores on a log, by its benchmark relations, against false ones.

`closure_scores.py` judges the back end's searches against the run's own final estimate, which
says nothing on a log the run maps wrong (the Freiburg hospital). Here the relations are the
judge. For a sample of relation pairs (t1, t2) it builds a submap as the back end does (the
scans within half `backend.submap_length` of path on either side of t1, at the run's own poses,
which are right locally even where the run drifts; the scans within 5 s of t2 are left out),
and scores the scan at t2:

- true: searched within 0.3 m and 3° of the pose the relation gives it (pose(t1) composed with
  the relation), so the score a closure at the right place reaches;
- false: searched in the back end's window (`backend.linear_window`, `angular_window_deg`)
  around the pose of a submap elsewhere: more than 50 m of path away from t1 and t2, and more
  than 10 m away in the run's estimate (a drifted estimate can still put the same place there,
  so read the false scores' maximum with that in mind).

Each group also prints its scores divided by what the submap's own central scan scores there at
its own pose (false ones: by their own submap's): a bar that would follow a log's level.
`--false-window M` searches the false matches within M metres instead of the back end's window.

Beside the scores, the share of the true match's end points that fall in cells the submap
observed at all (a scan that sees what the submap never held cannot score, whatever the
threshold). Groups: revisits (t1 and t2 at least `REVISIT_SECONDS` apart, what the back end
has to close), also split by whether the robot came back facing as before or the other way (a
180° laser then sees what the first pass had behind it), and nearby relations 10–60 s apart.
The scores are the search's (mean end-point occupancy probability, rust/src/loop_closure.rs),
with the map and back-end settings of the run's `config.yaml`.

    omnitof slam ../shared/data/intel.clf.bz2 --out RUN
    python benchmarks/closure_truth.py ../shared/data/intel.clf.bz2 ../shared/data/intel.relations RUN \
        [--pairs 60] [--false-window 8]
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from omnitof import _core
from omnitof.errors import OmnitofError
from omnitof.eval.relations import REVISIT_SECONDS, match_times, read_relations
from omnitof.geometry import compose
from omnitof.io.scans import read_scans
from omnitof.io.tum import read_tum
from omnitof.slam.config import load_config

TRUE_XY, TRUE_DEG = 0.3, 3.0
FALSE_PATH_M, FALSE_APART_M = 50.0, 10.0
LEAVE_OUT_S = 5.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log")
    parser.add_argument("relations")
    parser.add_argument("run", help="an `omnitof slam` results folder of this log (trajectory.tum, config.yaml)")
    parser.add_argument("--pairs", type=int, default=60, help="relations sampled per group")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sample")
    parser.add_argument("--bundle", type=float, default=0.0,
                        help="match the end points of every scan within this much path (m) of t2, placed by "
                        "the run's poses, instead of the one scan (0: the scan alone, as the back end does)")
    parser.add_argument("--false-window", type=float, default=None,
                        help="search the false matches within this half-width (m) instead of backend.linear_window")
    args = parser.parse_args()
    try:
        cfg = load_config(Path(args.run) / "config.yaml")
        scans = read_scans(args.log).scans
        traj = read_tum(Path(args.run) / "trajectory.tum")
        rel = read_relations(args.relations)
    except OmnitofError as err:
        raise SystemExit(f"error: {err}") from None
    if len(traj.timestamps) != len(scans) or not np.allclose(traj.timestamps, scans.timestamps, atol=1e-6):
        raise SystemExit(f"{args.run}/trajectory.tum does not hold one pose per scan of {args.log}")
    poses, stamps = traj.poses, traj.timestamps
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    # The relation's delta takes the pose at t1 to the pose at t2; the few with t1 > t2 are left out.
    forward = rel.t1 < rel.t2
    t1, t2, delta = rel.t1[forward], rel.t2[forward], rel.delta[forward]
    # match_times looks stamps up in sorted order: logs may hold them out of order (Intel: 631).
    (i_all, exact1), (j_all, exact2) = match_times(stamps, t1, 1e-3), match_times(stamps, t2, 1e-3)
    exact = exact1 & exact2

    m, b = cfg.map, cfg.backend
    max_range = min(m.max_range, scans.max_range)

    def submap(around: int, leave_out: float) -> _core.Submap:
        grid = _core.Submap(m.resolution, m.l_occ, m.l_free, m.l_min, m.l_max, max_range,
                            clear_no_echo=m.clear_no_echo, once_per_scan=m.once_per_scan,
                            spread_sigma=cfg.likelihood_field.sigma)
        near = (np.abs(path - path[around]) <= b.submap_length / 2) & (np.abs(stamps - leave_out) > LEAVE_OUT_S)
        for k in np.flatnonzero(near):
            grid.insert(poses[k], scans.scan_ranges(int(k)), scans.scan_angles(int(k)), sensor_pose=scans.sensor_pose)
        grid.finish()
        return grid

    def bundle(k: int) -> tuple[np.ndarray, np.ndarray]:
        """Scan k's (ranges, angles), or with --bundle the end points of its neighbours too, as
        readings of scan k's sensor (more context than one scan sees)."""
        if args.bundle <= 0:
            return scans.scan_ranges(k), scans.scan_angles(k)
        here = compose(poses[k], scans.sensor_pose)
        ranges, angles = [], []
        for n in np.flatnonzero(np.abs(path - path[k]) <= args.bundle):
            r, a = scans.scan_ranges(int(n)), scans.scan_angles(int(n))
            ok = np.isfinite(r) & (r < max_range)
            there = compose(poses[n], scans.sensor_pose)
            dx = there[0] + r[ok] * np.cos(there[2] + a[ok]) - here[0]
            dy = there[1] + r[ok] * np.sin(there[2] + a[ok]) - here[1]
            ranges.append(np.hypot(dx, dy))
            angles.append(np.arctan2(dy, dx) - here[2])
        return np.concatenate(ranges).astype(np.float32), np.concatenate(angles)

    def score(grid: _core.Submap, k: int, start: np.ndarray, xy: float, deg: float) -> tuple[float, float]:
        """(the best score in the window, the share of the end points there that fall in cells
        the submap observed at all)."""
        ranges, angles = bundle(k)
        found = grid.match_scan(ranges, angles, start, xy, math.radians(deg), 1e-6,
                                sensor_pose=scans.sensor_pose)
        if found is None:
            return 0.0, 0.0
        log_odds, ix0, iy0 = grid.to_dense()
        sensor = compose(np.asarray(found[0]), scans.sensor_pose)
        ok = np.isfinite(ranges) & (ranges < max_range)
        x = sensor[0] + ranges[ok] * np.cos(sensor[2] + angles[ok])
        y = sensor[1] + ranges[ok] * np.sin(sensor[2] + angles[ok])
        col = np.floor(x / m.resolution).astype(int) - ix0
        row = np.floor(y / m.resolution).astype(int) - iy0
        inside = (row >= 0) & (row < log_odds.shape[0]) & (col >= 0) & (col < log_odds.shape[1])
        observed = np.zeros(len(x), dtype=bool)
        observed[inside] = np.isfinite(log_odds[row[inside], col[inside]])
        return float(found[1]), float(observed.mean()) if len(x) else 0.0

    rng = np.random.default_rng(args.seed)
    gap = t2 - t1
    # A 180° laser that comes back facing the other way sees what the first pass had behind it.
    turned = np.abs(delta[:, 2]) > math.pi / 2
    revisit = exact & (gap >= REVISIT_SECONDS)
    groups = {
        "revisits": revisit,
        "revisits facing as before (|Δθ| ≤ 90°)": revisit & ~turned,
        "revisits facing the other way": revisit & turned,
        "nearby, 10-60 s": exact & (gap >= 10) & (gap < REVISIT_SECONDS),
    }
    print(f"{args.log}, run {args.run}; min_score {b.min_score}\n")
    print("| relations | pairs | true: score 10 / 50 / 90 % | true ≥ min_score | false: score 50 / 90 % / max | "
          "false ≥ min_score | true above false's 90 % | true: end points in observed cells, median |")
    print("|---|---|---|---|---|---|---|---|")
    for name, keep in groups.items():
        idx = np.flatnonzero(keep)
        idx = rng.choice(idx, min(args.pairs, len(idx)), replace=False) if len(idx) else idx
        true, false, observed, selfs, false_self = [], [], [], [], []
        for q in idx:
            i, j = int(i_all[q]), int(j_all[q])
            grid = submap(i, stamps[j])
            found, seen = score(grid, j, compose(poses[i], delta[q]), TRUE_XY, TRUE_DEG)
            own = score(grid, i, poses[i], 0.05, 1.0)[0]
            true.append(found)
            selfs.append(own)
            observed.append(seen)
            far = (np.abs(path - path[i]) > FALSE_PATH_M) & (np.abs(path - path[j]) > FALSE_PATH_M)
            for k in (i, j):
                far &= np.hypot(*(poses[:, :2] - poses[k, :2]).T) > FALSE_APART_M
            if far.any():
                o = int(rng.choice(np.flatnonzero(far)))
                fgrid = submap(o, stamps[j])
                false.append(score(fgrid, j, poses[o], args.false_window or b.linear_window, b.angular_window_deg)[0])
                false_self.append(false[-1] / max(score(fgrid, o, poses[o], 0.05, 1.0)[0], 1e-6))
        if not true:
            print(f"| {name} | 0 | | | | | | |")
            continue
        t, f = np.array(true), np.array(false) if false else np.zeros(1)
        print(f"| {name} | {len(t)} | {np.percentile(t, 10):.2f} / {np.median(t):.2f} / {np.percentile(t, 90):.2f} "
              f"| {np.mean(t >= b.min_score):.0%} | {np.median(f):.2f} / {np.percentile(f, 90):.2f} / {f.max():.2f} "
              f"| {np.mean(f >= b.min_score):.0%} | {np.mean(t > np.percentile(f, 90)):.0%} "
              f"| {np.median(observed):.0%} |")
        ts, fs = t / np.maximum(np.array(selfs), 1e-6), np.array(false_self) if false_self else np.zeros(1)
        print(f"|   relative to self | | {np.percentile(ts, 10):.2f} / {np.median(ts):.2f} / {np.percentile(ts, 90):.2f} "
              f"| self median {np.median(selfs):.2f} | {np.median(fs):.2f} / {np.percentile(fs, 90):.2f} / {fs.max():.2f} "
              f"| | {np.mean(ts > np.percentile(fs, 90)):.0%} | |")


if __name__ == "__main__":
    main()
