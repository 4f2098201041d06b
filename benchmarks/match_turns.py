"""Draw what the scan-matching filter saw at chosen integrated scans of a CARMEN log.

For each scan asked for, one panel: the best particle's map just before the step, the scan's
end points where the odometry predicts the robot (red) and where the filter put it (blue), and
the turn the step made against the odometry. It runs the preset's filter alone (no back end:
the back end changes nothing before its first loop closure) from the first scan up to the last
one asked for, with the scan delay estimated as `omnitof slam` does.

    python benchmarks/match_turns.py ../shared/data/fr-clinic_robotlaser.clf.bz2 --seed 0 \
        --scans 654 2385 --out turns.png
"""

from __future__ import annotations

import argparse
import math
import warnings

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from omnitof.geometry import compose, relative
from omnitof.io.carmen import read_carmen
from omnitof.slam import driver
from omnitof.slam.config import load_config, parse_setting, settings_overrides
from omnitof.slam.timing import estimate_scan_delay, retime_odometry


def end_points(scans, k: int, robot: np.ndarray, max_range: float) -> np.ndarray:
    ranges, angles = scans.scan_ranges(k), scans.scan_angles(k)
    keep = np.isfinite(ranges) & (ranges > 0) & (ranges < max_range)
    sensor = compose(robot, scans.sensor_pose)
    bearing = angles[keep] + sensor[2]
    return np.c_[sensor[0] + ranges[keep] * np.cos(bearing), sensor[1] + ranges[keep] * np.sin(bearing)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("log")
    ap.add_argument("--scans", type=int, nargs="+", required=True, help="integrated scans to draw (the nearest at or after each)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--preset", default="laser180-scanmatch")
    ap.add_argument("--particles", type=int, default=30)
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="one configuration field over the preset, as `omnitof slam --set`")
    ap.add_argument("--half-width", type=float, default=15.0, help="half the side of each panel (m)")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader's notes on the log are not what this script is about
        scans = read_carmen(args.log).scans
    scans = retime_odometry(scans, estimate_scan_delay(scans).delay)
    overrides = settings_overrides(dict(parse_setting(text) for text in args.set), "--set")
    overrides.setdefault("filter", {}).update(particles=args.particles, seed=args.seed)
    overrides.setdefault("backend", {})["enabled"] = False
    cfg = load_config(preset=args.preset, overrides=overrides)
    integrated = driver.select_scans(scans.odometry, cfg.filter.linear_update, math.radians(cfg.filter.angular_update_deg))
    wanted = sorted({int(integrated[np.searchsorted(integrated, s)]) for s in args.scans if s <= integrated[-1]})
    pf = driver._make_filter(scans, cfg)
    between = driver._Between(scans, cfg) if cfg.filter.match_between else None
    res, max_range = cfg.map.resolution, cfg.sensor_model.max_range
    fig, axes = plt.subplots(1, len(wanted), figsize=(6 * len(wanted), 6), squeeze=False)
    panels = iter(axes[0])
    prev = scans.odometry[integrated[0]]
    for k in integrated:
        if k > wanted[-1]:
            break
        if between is not None:
            between.match_up_to(pf, int(k))
        cur = scans.odometry[k]
        drawing = int(k) in wanted
        if drawing:
            predicted = compose(pf.best_pose(), relative(prev, cur))
            log_odds, ix0, iy0 = pf.best_map()
        own = scans.scan_angles(k) if scans.per_scan_geometry else None
        pf.step(prev, cur, scans.scan_ranges(k), int(k), angles=own)
        prev = cur
        if not drawing:
            continue
        taken = pf.best_pose()
        turn = math.degrees(math.remainder(taken[2] - predicted[2], math.tau))
        ax = next(panels)
        h, w = log_odds.shape
        free = np.where(np.isnan(log_odds), 0.5, 1.0 / (1.0 + np.exp(log_odds)))
        ax.imshow(free, origin="lower", cmap="gray", vmin=0, vmax=1,
                  extent=[ix0 * res, (ix0 + w) * res, iy0 * res, (iy0 + h) * res])
        for pose, colour, label in ((predicted, "tab:red", "scan at the odometry's prediction"),
                                    (taken, "tab:blue", "scan where the filter put it")):
            pts = end_points(scans, int(k), pose, max_range)
            ax.plot(pts[:, 0], pts[:, 1], ".", color=colour, ms=3, label=label)
            ax.plot(*pose[:2], "o", color=colour, ms=5)
        ax.set_xlim(predicted[0] - args.half_width, predicted[0] + args.half_width)
        ax.set_ylim(predicted[1] - args.half_width, predicted[1] + args.half_width)
        ax.set_title(f"scan {k}, seed {args.seed}: turned {turn:+.1f}° against the odometry")
        ax.set_xlabel("x [m]")
        ax.legend(loc="lower left", fontsize=8)
        print(f"scan {k}: predicted {np.round(predicted, 3).tolist()}, taken {np.round(taken, 3).tolist()}, turn {turn:+.2f} deg")
    fig.tight_layout()
    fig.savefig(args.out, dpi=90, bbox_inches="tight")


if __name__ == "__main__":
    main()
