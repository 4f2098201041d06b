"""The scan extraction's speed with the multipath compensation's options (omnitof.scan.multipath):
without the compensation, as shipped, with `visibility`, with `beyond_view`, and with both.

The frames are rendered once (every effect of the camera on, spread over the world's drive, as
`tof_errors.py` renders them); each extractor then takes all of them in turn, --runs times, so
that the machine's drift falls on every variant alike. Reported: frames/s, the median of the
runs and their range, and the ratio to "as shipped" in the same run.

With --keyframes, instead: the 3D filter's keyframes, whose rays and scan both come from
the frame (`scan.tof_input`), with the compensation as shipped: corrected once for both
(`ScanExtractor.corrected_distances`, as reading a bag does now) against corrected for each
(as it did before), every frame a keyframe.

Usage:
    python benchmarks/multipath_speed.py [--world corridor1] [--frames 30] [--runs 7] [--keyframes]
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
    parser.add_argument("--keyframes", action="store_true", help="rays and scans of keyframes, corrected once or twice")
    args = parser.parse_args()
    renderer, _, rendered = frames(load_world(args.world), ToFErrors.realistic(), args.frames)
    d = np.stack([f.distance for f in rendered])
    a = np.stack([f.amplitude for f in rendered])
    cal = Calibration.from_rig(renderer.rig)
    if args.keyframes:
        keyframes(args, ScanExtractor.from_calibration(cal, multipath=compensation(renderer, True)), d, a)
        return
    extractors = {
        label: ScanExtractor.from_calibration(
            cal, **({} if change is None else {"multipath": {**compensation(renderer, True), **change}})
        )
        for label, change in VARIANTS.items()
    }
    runs = {label: (lambda e=extractor: e.extract_many(d, a)) for label, extractor in extractors.items()}
    print(f"# {args.world}, {len(d)} frames, {args.runs} runs, load {os.getloadavg()[0]:.1f}")
    timed(runs, args.runs, len(d), ("compensation", "frames/s"), "as shipped")


def timed(runs: dict, repeats: int, count: int, header: tuple[str, str], baseline: str) -> None:
    """Time each of `runs` (label: callable) in turn, `repeats` times, and print the table: rate
    of `count` items per second, median (min–max), and time against `baseline`'s."""
    seconds: dict[str, list[float]] = {label: [] for label in runs}
    for _ in range(repeats):
        for label, run in runs.items():
            t = time.perf_counter()
            run()
            seconds[label].append(time.perf_counter() - t)
    base = statistics.median(seconds[baseline])
    print(f"| {header[0]} | {header[1]}, median (min–max) | time / {baseline} |")
    print("|---|---|---|")
    for label, s in seconds.items():
        print(f"| {label} | {count / statistics.median(s):.1f} ({count / max(s):.1f}–{count / min(s):.1f}) | "
              f"{statistics.median(s) / base:.2f} |")


def keyframes(args: argparse.Namespace, extractor: ScanExtractor, d: np.ndarray, a: np.ndarray) -> None:
    """Rays and scans of every frame: corrected once for both, or once for each."""

    def once() -> None:
        fixed = extractor.corrected_distances(d, a)
        for k in range(len(d)):
            extractor.rays(fixed[k], a[k], corrected=True)
        extractor.extract_many(fixed, a, corrected=np.ones(len(d), dtype=bool))

    def twice() -> None:
        for k in range(len(d)):
            extractor.rays(d[k], a[k])
        extractor.extract_many(d, a)

    print(f"# {args.world}, {len(d)} keyframes, compensation as shipped, {args.runs} runs, load {os.getloadavg()[0]:.1f}")
    timed({"corrected once (now)": once, "corrected for each (before)": twice}, args.runs, len(d),
          ("rays and scan of each keyframe", "keyframes/s"), "corrected once (now)")


if __name__ == "__main__":
    main()
