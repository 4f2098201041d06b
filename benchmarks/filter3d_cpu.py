"""CPU time per integrated frame of the 3D filter and the 2D one: on a machine shared with other
jobs the wall clock measures the load more than the filter; the CPU seconds of all the process's
threads per frame (time.process_time) say what an idle machine would take (divided by the
cores the work spreads over, at best).

Office, drive seed 0, the true rig (the calibration does not change the cost), preset tof3d with
30 particles: the odometry proposal, and the scan-matching proposal with climb_stride 1 and 3.
The 2D filter runs first on the same scans as the baseline.

Usage:
    python benchmarks/filter3d_cpu.py [--world office] [--seed 0] [--particles 30]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from datetime import date
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import filter3d as bench  # noqa: E402  (benchmarks/filter3d.py: the same prepared drive)

from omnitof.slam import run_slam  # noqa: E402
from omnitof.slam.config import load_config  # noqa: E402
from omnitof.slam.filter3d import run_slam3d  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--particles", type=int, default=30)
    args = parser.parse_args(argv)
    print(f"# {date.today()} · {os.cpu_count()} cores · load {os.getloadavg()[0]:.1f} at start")
    print(f"# command: python benchmarks/filter3d_cpu.py {' '.join(argv if argv is not None else sys.argv[1:])}")
    base = load_config(preset="tof3d")
    _, data, _ = bench.prepare(args.world, args.seed, "true", base, None)
    print("\n| proposal | climb_stride | 3D CPU s/frame | 3D wall s/frame (median) | 2D CPU s/frame | 2D wall s/frame | load |")
    print("|---|---|---|---|---|---|---|")
    for proposal, climb in (("odometry", 1), ("scanmatch", 1), ("scanmatch", 3)):
        cfg = load_config(preset="tof3d", overrides={"filter": {"proposal": proposal, "particles": args.particles,
                                                                "seed": args.seed},
                                                     "filter3d": {"climb_stride": climb}})
        c0, w0 = time.process_time(), time.perf_counter()
        flat = run_slam(data.scans, cfg)
        n2 = flat.stats["integrated"]
        cpu2, wall2 = (time.process_time() - c0) / n2, (time.perf_counter() - w0) / n2
        s = run_slam3d(data.scans, data.cloud_frames, data.clouds, cfg).result.stats
        print(f"| {proposal} | {climb} | {s['cpu_seconds_per_integrated_frame']:.3f} "
              f"| {s['seconds_per_integrated_frame']['median']:.3f} | {cpu2:.4f} | {wall2:.4f} "
              f"| {os.getloadavg()[0]:.1f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
