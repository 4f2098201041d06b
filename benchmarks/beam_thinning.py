"""Scans denser than the map: what thinning them does to the filter (`map.thin_beams`).

    python benchmarks/beam_thinning.py [--seeds 0 1 2] [--scans N] [--presets sim2d laser180-scanmatch]
                                       [--beams 181 1081 20001] [--modes dense always off]
                                       [--set SECTION.FIELD=VALUE ...]

The simulated corridor loop (omnitof.sim.laser2d, seed 0: its odometry and ground truth)
scanned again at the true poses by lasers of 181 beams over 180° (the loop's own), 1081 over
270° (a Hokuyo UTM-30LX's geometry) and 20 001 over 180° (a scan flattened from a denser
sensor), 1 cm noise, 8 m range. Each is run with `map.thin_beams` dense (the default: only
scans above map.max_beams 8192 are thinned), always (every scan to one beam per end-point cell
of half the resolution) and, for the 20 001-beam laser, off. Prints a Markdown table: the
trajectory's mean error to the truth (ATE), the share of occupied map cells within 10 cm of a
wall, the median beams the filter used per scan, and the run's seconds; per seed.
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings

import numpy as np

from omnitof.eval.floorplan import wall_agreement
from omnitof.eval.trajectory import absolute_trajectory_error
from omnitof.sim.laser2d import beam_angles, corridor_loop_world, make_loop_dataset, simulate_scans
from omnitof.slam import run_slam
from omnitof.slam.config import load_config, parse_setting, settings_overrides
from omnitof.slam.thinning import thin_dense_scans
from omnitof.types import ScanSequence

LASERS = [(181, 180.0), (1081, 270.0), (20_001, 180.0)]


def _merged(base: dict, update: dict) -> dict:
    """`base` with `update`'s sections merged in, field by field."""
    return {k: {**base.get(k, {}), **update.get(k, {})} for k in {*base, *update}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--scans", type=int, default=None, help="the loop's first N scans (default: all)")
    parser.add_argument("--presets", nargs="+", default=["sim2d", "laser180-scanmatch"])
    parser.add_argument("--beams", type=int, nargs="+", default=[b for b, _ in LASERS], help="which lasers")
    parser.add_argument("--modes", nargs="+", default=["dense", "always", "off"], help="which thin_beams")
    parser.add_argument("--set", nargs="+", default=[], metavar="SECTION.FIELD=VALUE",
                        help="settings of every run, as omnitof slam --set (e.g. map.once_per_scan=true)")
    args = parser.parse_args()
    loop = make_loop_dataset(seed=0)
    if args.scans is not None:
        loop = loop.slice(0, args.scans)
    world = corridor_loop_world()
    extra = settings_overrides(dict(parse_setting(item) for item in args.set), "--set")
    print(f"settings: {' '.join(args.set) or 'none'}; odometry: ATE mean {absolute_trajectory_error(loop.odometry, loop.ground_truth).mean:.3f} m, "
          f"{len(loop)} scans\n")
    print("| preset | laser | thin_beams | beams used (median) | ATE mean per seed (m) | walls within 10 cm per seed | s per run (median) |")
    print("|---|---|---|---|---|---|---|")
    for preset in args.presets:
        for beams, fov in (laser for laser in LASERS if laser[0] in args.beams):
            angles = beam_angles(beams, fov)
            ranges = simulate_scans(world, loop.ground_truth, angles, max_range=8.0, range_noise=0.01, seed=3)
            scans = ScanSequence(timestamps=loop.timestamps, ranges=ranges, angles=angles, odometry=loop.odometry,
                                 max_range=8.0, ground_truth=loop.ground_truth, source=f"{beams} beams")
            for mode in (m for m in args.modes if beams > 8192 or m != "off"):
                errors, walls, seconds = [], [], []
                for seed in args.seeds:
                    cfg = load_config(preset=preset, overrides=_merged(extra, {"filter": {"seed": seed},
                                                                               "map": {"thin_beams": mode}}))
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        used, _ = thin_dense_scans(scans, cfg)
                        start = time.perf_counter()
                        result = run_slam(scans, cfg)
                    seconds.append(time.perf_counter() - start)
                    errors.append(absolute_trajectory_error(result.trajectory.poses, loop.ground_truth).mean)
                    walls.append(wall_agreement(result.map, world.distance_to_walls, tolerance=0.1).near_fraction)
                counts = used.beam_counts if used.beam_counts is not None else np.full(len(used), used.n_beams)
                print(f"| {preset} | {beams} over {fov:g}° | {mode} | {int(np.median(counts))} | "
                      f"{' / '.join(f'{e:.3f}' for e in errors)} | {' / '.join(f'{w:.2f}' for w in walls)} | "
                      f"{statistics.median(seconds):.1f} |", flush=True)


if __name__ == "__main__":
    main()
