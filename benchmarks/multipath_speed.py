"""The scan extraction's speed with the multipath compensation's options (omnitof.scan.multipath):
without the compensation, as shipped, with `visibility`, with `beyond_view`, and with both.

The frames are rendered once (every effect of the camera on, spread over the world's drive, as
`tof_errors.py` renders them); each extractor then takes all of them in turn, --runs times, so
that the machine's drift falls on every variant alike. Reported: frames/s, the median of the
runs and their range, and the ratio to "as shipped" in the same run.

Usage:
    python benchmarks/multipath_speed.py [--world corridor1] [--frames 30] [--runs 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from omnitof.calibration import Calibration
from omnitof.scan.extract import ScanExtractor
from omnitof.sensor.tof_errors import ToFErrors
from omnitof.sim.worlds import load_world
from tof_errors import compensation, frames

VARIANTS = {
    "no compensation": None,
    "as shipped": {},
    "visibility": {"visibility": True},
    "beyond_view": {"beyond_view": True},
    "visibility + beyond_view": {"visibility": True, "beyond_view": True},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="corridor1")
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--runs", type=int, default=7)
    args = parser.parse_args()
    renderer, _, rendered = frames(load_world(args.world), ToFErrors.realistic(), args.frames)
    d = np.stack([f.distance for f in rendered])
    a = np.stack([f.amplitude for f in rendered])
    cal = Calibration.from_rig(renderer.rig)
    extractors = {
        label: ScanExtractor.from_calibration(
            cal, **({} if change is None else {"multipath": {**compensation(renderer, True), **change}})
        )
        for label, change in VARIANTS.items()
    }
    seconds: dict[str, list[float]] = {label: [] for label in VARIANTS}
    for _ in range(args.runs):
        for label, extractor in extractors.items():
            t = time.perf_counter()
            extractor.extract_many(d, a)
            seconds[label].append(time.perf_counter() - t)
    shipped = statistics.median(seconds["as shipped"])
    print(f"# {args.world}, {len(d)} frames, {args.runs} runs, load {os.getloadavg()[0]:.1f}")
    print("| compensation | frames/s, median (min–max) | time / as shipped |")
    print("|---|---|---|")
    for label, s in seconds.items():
        print(f"| {label} | {len(d) / statistics.median(s):.1f} ({len(d) / max(s):.1f}–{len(d) / min(s):.1f}) | "
              f"{statistics.median(s) / shipped:.2f} |")


if __name__ == "__main__":
    main()
