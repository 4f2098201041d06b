"""The estimated calibration against the true rig, measured on the scans instead of the maps.

For each world (drive seed 0 unless told), the drive is rendered with the demo's ToF errors and
extracted twice, as `omnitof demo` does it: with the calibration estimated from rendered targets
(refined, with the wall-fitted distance correction; `world_filters.extracted_scans`, cached) and
with the true rig given the same wall-fitted correction (`extracted_scans(..., true_rig=True)`).
Every bin that both the scan and the exact floor plan at the slice height (from the true pose,
`world_filters.ideal_scans`) have a range for is compared: the median
and 90th percentile of |error| and the share within 5 cm. Why: the maps' share of cells within
5 cm of a wall swings by tens of points between filter seeds (BENCHMARKS.md, issue 13), far more
than a calibration moves it, so the maps cannot tell two calibrations apart; the scans can.

    python benchmarks/calibration_scans.py --worlds office corridor1 [--drive 0] [--cache results/world_scans]

Prints one JSON line per (world, calibration).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from omnitof.sim.worlds import load_world

sys.path.insert(0, str(Path(__file__).resolve().parent))
from world_filters import extracted_scans, ideal_scans  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--worlds", nargs="+", default=["office", "corridor1"])
    parser.add_argument("--drive", type=int, default=0)
    parser.add_argument("--cache", type=Path, default=Path("results/world_scans"))
    args = parser.parse_args(argv)
    args.cache.mkdir(parents=True, exist_ok=True)
    for name in args.worlds:
        estimated = extracted_scans(name, args.drive, args.cache)
        exact = ideal_scans(load_world(name), estimated).ranges
        true_rig = extracted_scans(name, args.drive, args.cache, true_rig=True)
        for label, scans in (("estimated", estimated), ("true rig", true_rig)):
            both = np.isfinite(scans.ranges) & np.isfinite(exact)
            error = np.abs(scans.ranges[both] - exact[both])
            print(json.dumps({
                "world": name, "drive": args.drive, "calibration": label, "bins": int(both.sum()),
                "readings_per_frame": round(float(np.isfinite(scans.ranges).sum(axis=1).mean()), 1),
                "median_mm": round(1000 * float(np.median(error)), 1),
                "p90_mm": round(1000 * float(np.percentile(error, 90)), 1),
                "within_5cm_pct": round(100 * float(np.mean(error <= 0.05)), 1),
            }), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
