"""What the back end's loop-closure searches score on a log, true matches against false ones.

Runs `omnitof slam LOG` (any preset with the back end) and, beside every search the back end
makes, searches the same scan in the same submap and window with no score threshold, so that
the best pose there is known even where the back end rejects it. Once the run has finished,
each such match is judged against the run's final (optimised) estimate: "true" where it puts the
scan within 0.2 m and 2° of where the estimate does. That judgement is only as good as the final
map: use it on logs the preset maps well (Intel, Freiburg 079); elsewhere read it as agreement
with the run's own answer. For every finished submap it also scores the submap's own scans at
their insertion poses (the "self-score": what a perfect match scores in that submap).

Per match it records the score (the search's mean end-point probability), the share of the
scan's end points that fall in cells the submap observed at all ("coverage"), and the score of
those alone, estimated as (score − 0.1 · (1 − coverage)) / coverage (never-observed cells count
0.1 in the search).

    OMNITOF_DATA=../shared/data python benchmarks/closure_scores.py ../shared/data/intel.clf.bz2 --seed 0

Prints quantiles of each quantity for true and false matches, and how many of each a few
acceptance rules would let through; `--json FILE` keeps every record.
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile

import numpy as np

from omnitof.geometry import compose, relative, wrap_angle
from omnitof.slam import backend as backend_module

# Where a never-observed cell's probability sits in the search (rust/src/loop_closure.rs).
UNKNOWN_PROBABILITY = 0.1
TRUE_XY, TRUE_DEG = 0.2, 2.0


class Recorder:
    """Hooks into PoseGraphBackend (the driver builds it; there is no other seam) and records."""

    def __init__(self) -> None:
        self.self_scores: list[float] = []
        self.matches: list[dict] = []
        Backend = backend_module.PoseGraphBackend
        build, search, finish = Backend._build, Backend._search, Backend.finish
        rec = self

        def _build(backend, sub, pf):
            build(backend, sub, pf)
            rec.on_build(backend, sub)

        def _search(backend, j):
            rec.on_search(backend, j)
            return search(backend, j)

        def _finish(backend, pf):
            out = finish(backend, pf)
            rec.on_finish(backend)
            return out

        Backend._build, Backend._search, Backend.finish = _build, _search, _finish

    def on_build(self, backend, sub) -> None:
        scores = []
        for j, pose in zip(sub.nodes, sub.poses):
            k = backend.scan_of[j]
            # A window of one cell and one degree: the score at the insertion pose.
            m = sub.grid.match_scan(backend.scans.scan_ranges(k), backend.scans.scan_angles(k), pose,
                                    1.01 * sub.grid.resolution, math.radians(1.0), 0.0,
                                    sensor_pose=backend.scans.sensor_pose, refine=False)
            scores.append(0.0 if m is None else m[1])
        sub.self_score = float(np.median(scores))
        self.self_scores.append(sub.self_score)

    def on_search(self, backend, j: int) -> None:
        """The back end's local search of node j (the global one is not probed), without a threshold."""
        if not backend.submaps:
            return
        cfg, k = backend.cfg, backend.scan_of[j]
        for s in backend._candidates(j, cfg.search_radius)[: cfg.max_closures_per_scan]:
            sub = backend.submaps[s]
            initial = compose(sub.anchor_pose, relative(backend.estimate[sub.first], backend.estimate[j]))
            m = sub.grid.match_scan(backend.scans.scan_ranges(k), backend.scans.scan_angles(k), initial,
                                    cfg.linear_window, math.radians(cfg.angular_window_deg), 0.0,
                                    sensor_pose=backend.scans.sensor_pose, field_sigma=backend.field_sigma)
            if m is None:
                continue
            pose = np.asarray(m[0])
            self.matches.append({
                "node": j, "anchor": sub.first, "score": float(m[1]), "self_score": sub.self_score,
                "coverage": coverage(backend, sub, k, pose), "measured": relative(sub.anchor_pose, pose).tolist(),
            })

    def on_finish(self, backend) -> None:
        estimate = np.asarray(backend.estimate)
        for r in self.matches:
            d = relative(estimate[r["anchor"]], estimate[r["node"]]) - np.asarray(r["measured"])
            r["true"] = bool(math.hypot(d[0], d[1]) < TRUE_XY and abs(math.degrees(wrap_angle(d[2]))) < TRUE_DEG)
            c = r["coverage"]
            r["known_score"] = (r["score"] - UNKNOWN_PROBABILITY * (1 - c)) / c if c > 0 else 0.0


def coverage(backend, sub, k: int, pose: np.ndarray) -> float:
    """Share of scan k's end points (robot at `pose`) in cells the submap observed."""
    if not hasattr(sub, "dense"):
        sub.dense = sub.grid.to_dense()
    log_odds, ix0, iy0 = sub.dense
    res = sub.grid.resolution
    sp = compose(pose, backend.scans.sensor_pose)
    r = backend.scans.scan_ranges(k).astype(np.float64)
    a = backend.scans.scan_angles(k)
    ok = (r > 0) & (r < backend.max_range)
    if not ok.any():
        return 0.0
    x = sp[0] + r[ok] * np.cos(sp[2] + a[ok])
    y = sp[1] + r[ok] * np.sin(sp[2] + a[ok])
    ix = np.floor(x / res).astype(np.int64) - ix0
    iy = np.floor(y / res).astype(np.int64) - iy0
    inside = (ix >= 0) & (iy >= 0) & (ix < log_odds.shape[1]) & (iy < log_odds.shape[0])
    known = np.zeros(len(x), dtype=bool)
    known[inside] = ~np.isnan(log_odds[iy[inside], ix[inside]])
    return float(known.mean())


def quantiles(v: np.ndarray) -> str:
    return " / ".join(f"{q:.2f}" for q in np.percentile(v, [5, 25, 50, 75, 95])) if len(v) else "-"


def report(rec: Recorder, min_score: float) -> None:
    s = np.asarray(rec.self_scores)
    print(f"submaps: {len(s)}, self-score median {np.median(s):.3f} (10th-90th percentile "
          f"{np.percentile(s, 10):.3f}-{np.percentile(s, 90):.3f})")
    if not rec.matches:
        print("no search")
        return
    truth = np.array([r["true"] for r in rec.matches])
    gap = np.array([r["node"] - r["anchor"] for r in rec.matches])
    print(f"searches: {len(truth)}, true {truth.sum()}, false {(~truth).sum()}; "
          f"revisits (more than 100 nodes after the submap's first): {(gap > 100).sum()}")
    print("| quantity | true: 5 / 25 / 50 / 75 / 95 % | false: 5 / 25 / 50 / 75 / 95 % |")
    print("|---|---|---|")
    for name in ("score", "coverage", "known_score"):
        v = np.array([r[name] for r in rec.matches])
        print(f"| {name} | {quantiles(v[truth])} | {quantiles(v[~truth])} |")
    ratio = np.array([r["score"] / r["self_score"] for r in rec.matches])
    print(f"| score / self-score | {quantiles(ratio[truth])} | {quantiles(ratio[~truth])} |")
    score = np.array([r["score"] for r in rec.matches])
    cov = np.array([r["coverage"] for r in rec.matches])
    known = np.array([r["known_score"] for r in rec.matches])
    rules = [(f"score >= {min_score} (the preset)", score >= min_score)]
    rules += [(f"score / self-score >= {t}", ratio >= t) for t in (0.75, 0.85)]
    rules += [(f"coverage >= 0.5 and known_score >= {t}", (cov >= 0.5) & (known >= t)) for t in (0.65, 0.75)]
    print("\n| accept where | true | false | revisits |\n|---|---|---|---|")
    for name, a in rules:
        print(f"| {name} | {np.sum(a & truth)} | {np.sum(a & ~truth)} | {np.sum(a & (gap > 100))} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--preset", default=None, help="default: the one `omnitof slam` picks")
    parser.add_argument("--json", help="write every record here")
    args = parser.parse_args()
    rec = Recorder()
    from omnitof.cli import main as cli

    with tempfile.TemporaryDirectory() as out:
        argv = ["slam", args.log, "--seed", str(args.seed), "--out", out, "--quiet"]
        cli(argv + (["--preset", args.preset] if args.preset else []))
    from omnitof.slam_run import default_preset, slam_config

    min_score = slam_config(preset=args.preset or default_preset(args.log)).backend.min_score
    report(rec, min_score)
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"self_scores": rec.self_scores, "matches": rec.matches}, f)


if __name__ == "__main__":
    main()
