"""Range readings from ToF frames (omnitof.scan): speed and accuracy on the bundled worlds.

Frames are rendered with the default rig (SR4000 wide lens, four mirrors at 56°, 4 sub-rays per
pixel, sensor noise on) at poses spread evenly along each world's robot loop, heading along the
loop. Then, per world:

- speed: ScanExtractor.extract_many over the frames (repeated to --batch frames), wall-clock,
  median and spread over --runs runs, in frames per second (one process, numpy, one core);
- accuracy: each 1° bin's range against the exact horizontal distance at the slice height to
  the nearest surface along the bin's bearing (World.horizontal_distance; robot bearing + θ =
  world bearing), grouped by the material kind that surface is made of (the renderer's own
  first-surface cast at the slice height): bins, share without reading, median |error|, share
  within 5 cm, median signed error.

With --table1, also the paper's Table I and the floor-plan metrics for the two corridor loops,
on maps built from these scans with the *true* poses (the filter with one particle and no motion
noise: known-pose mapping, so the numbers measure the scans and the grid, not SLAM's drift):
each sequence (sim.sequence.make_sequence, seed 0) is rendered in full, turned into scans
(scan.scans_from_frames) and mapped (preset "paper", sensor and map max_range 7 m).

Usage:
    python benchmarks/scan.py [--runs 7] [--frames 24] [--batch 512] [--worlds room office ...]
                              [--table1]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import time

import numpy as np

from omnitof.scan import ScanExtractor
from omnitof.sim.render import Renderer
from omnitof.sim.worlds import World, load_world, world_names
from omnitof.sim.sequence import poses_along_loop


def accuracy(world: World, renderer: Renderer, extractor: ScanExtractor, poses: np.ndarray,
             ranges: np.ndarray) -> dict[str, tuple[int, float, float, float, float]]:
    """kind → (bins, share empty, median |error| m, share within 5 cm, median error m)."""
    h = extractor.settings.height
    errors, kinds = [], []
    for pose, r in zip(poses, ranges):
        bearings = extractor.angles + pose[2]
        truth = world.horizontal_distance(pose[:2], bearings, h)
        directions = np.column_stack([np.cos(bearings), np.sin(bearings), np.zeros(len(bearings))])
        _, names = renderer.first_surface(np.tile([pose[0], pose[1], h], (len(bearings), 1)), directions)
        kinds.append([world.materials[n].kind if n else "none" for n in names])
        errors.append(r - truth)
    e, k = np.concatenate(errors), np.concatenate(kinds)
    out = {}
    for kind in ("matte", "metal", "glass", "grid", "none", "all"):
        sel = np.ones(len(k), bool) if kind == "all" else k == kind
        if not sel.any():
            continue
        seen = sel & np.isfinite(e)
        med = float(np.median(np.abs(e[seen]))) if seen.any() else float("nan")
        within = float(np.mean(np.abs(e[seen]) < 0.05)) if seen.any() else float("nan")
        bias = float(np.median(e[seen])) if seen.any() else float("nan")
        out[kind] = (int(sel.sum()), 1.0 - seen.sum() / sel.sum(), med, within, bias)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--frames", type=int, default=24, help="rendered frames per world")
    parser.add_argument("--batch", type=int, default=512, help="frames per timed extract_many call")
    parser.add_argument("--worlds", nargs="*", default=world_names())
    parser.add_argument("--table1", action="store_true", help="also Table I on known-pose maps")
    args = parser.parse_args()
    print(f"# {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {platform.processor() or platform.machine()}, "
          f"{os.cpu_count()} cores, numpy {np.__version__}")
    extractor = ScanExtractor.from_rig()
    s = extractor.settings
    print(f"# slice {s.height} ± {s.band} m, statistic {s.statistic}, min_amplitude {s.min_amplitude}, "
          f"min_amplitude_1m {s.min_amplitude_1m}, "
          f"range {s.min_range}..{s.max_range} m, min_points {s.min_points}")
    print(f"{'world':10s} {'kind':6s} {'bins':>6s} {'empty':>6s} {'med|e|':>8s} {'<5cm':>6s} {'median e':>9s}")
    speeds = {}
    for name in args.worlds:
        world = load_world(name)
        renderer = Renderer(world)
        poses = poses_along_loop(world, args.frames)
        frames = renderer.render_many(poses, seed=0)
        d = np.stack([f.distance for f in frames])
        a = np.stack([f.amplitude for f in frames])
        ranges = extractor.extract_many(d, a)
        for kind, (n, empty, med, within, bias) in accuracy(world, renderer, extractor, poses, ranges).items():
            print(f"{name:10s} {kind:6s} {n:6d} {empty:6.1%} {100 * med:6.2f}cm {within:6.1%} {100 * bias:+7.2f}cm")
        reps = -(-args.batch // len(d))
        big_d, big_a = np.tile(d, (reps, 1, 1))[: args.batch], np.tile(a, (reps, 1, 1))[: args.batch]
        extractor.extract_many(big_d, big_a)  # warm up
        times = []
        for _ in range(args.runs):
            start = time.perf_counter()
            extractor.extract_many(big_d, big_a)
            times.append(time.perf_counter() - start)
        speeds[name] = [args.batch / t for t in times]
    print()
    print(f"extract_many, {args.batch} frames per call, {args.runs} runs: frames/s median (min–max)")
    for name, fps in speeds.items():
        print(f"{name:10s} {statistics.median(fps):8.0f}  ({min(fps):.0f}–{max(fps):.0f})")
    if args.table1:
        known_pose_table1(extractor)


def known_pose_table1(extractor: ScanExtractor) -> None:
    """Table I and floor-plan metrics of corridor1 and corridor2 mapped with the true poses."""
    import dataclasses

    from omnitof.slam.config import load_config
    from omnitof.eval.floorplan import wall_agreement, wall_coverage
    from omnitof.eval.table1 import format_table1, table1
    from omnitof.scan import scans_from_frames
    from omnitof.sim.laser2d import World2D
    from omnitof.sim.sequence import make_sequence, render_sequence
    from omnitof.slam import run_slam

    cfg = load_config(preset="paper", overrides={
        "filter": {"particles": 1},
        "motion": {"alpha1": 0.0, "alpha2": 0.0, "alpha3": 0.0, "alpha4": 0.0},
        "sensor_model": {"max_range": 7.0},
        "map": {"max_range": 7.0},
    })
    results = {}
    print()
    for name in ("corridor1", "corridor2"):
        world = load_world(name)
        sequence = make_sequence(world, seed=0)
        start = time.perf_counter()
        scans = scans_from_frames(extractor, render_sequence(sequence, Renderer(world)), source=name)
        seconds = time.perf_counter() - start
        assert scans.ground_truth is not None  # simulated frames carry their true poses
        scans = dataclasses.replace(scans, odometry=scans.ground_truth.copy())
        occ = run_slam(scans, cfg).map
        results[name] = table1(occ, world.landmarks)
        walls = world.wall_segments()
        agree = wall_agreement(occ, World2D(walls).distance_to_walls, tolerance=0.05)
        cover = wall_coverage(occ, walls, sequence.ground_truth, extractor.settings.max_range,
                              occluders=world.segments_at(extractor.settings.height))
        print(f"{name}: {len(scans)} frames rendered and scanned in {seconds:.0f} s; bins without reading "
              f"{np.mean(~np.isfinite(scans.ranges)):.1%}; occupied cells within 5 cm of a wall "
              f"{agree.near_fraction:.1%} (mean {100 * agree.mean_distance:.1f} cm); wall length in view "
              f"{cover.seen_length:.0f} m, held by the map {cover.fraction:.1%} (mean distance "
              f"{100 * cover.mean_distance:.1f} cm)")
    print()
    print("Table I on known-pose maps:")
    print(format_table1(results))


if __name__ == "__main__":
    main()
